"""Checkpoints: atomic round trip, the compressed shipping formats, a full disk."""
import errno
import gc
import shutil
import subprocess

import pytest
import torch

from odg_ros.network import ODG, checkpoint
from odg_ros.network.checkpoint import (dequantize_int8, grow_state_dict, load_model,
                                       quantize_int8, save_checkpoint)

from testing.helpers import model_inputs, tiny_config


def test_round_trip_exact(tmp_path):
    model = ODG(tiny_config())
    save_checkpoint(tmp_path / "a.pt", model, extra={"step": 3})
    loaded, cfg = load_model(tmp_path / "a.pt")
    assert cfg == model.cfg
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k]), k


def test_int8_weights_within_half_a_step_per_channel():
    g = torch.Generator().manual_seed(0)
    w = torch.randn(16, 8, 3, 3, generator=g) * torch.logspace(-3, 1, 16)[:, None, None, None]
    back = dequantize_int8(quantize_int8(w))
    step = w.abs().reshape(16, -1).amax(1) / 127
    assert ((back - w).abs().reshape(16, -1).amax(1) <= step / 2 + 1e-9).all()
    zero = dequantize_int8(quantize_int8(torch.zeros(4, 4)))
    assert torch.equal(zero, torch.zeros(4, 4))


def test_int8_checkpoint_is_small_and_predicts_like_the_original(tmp_path):
    cfg = tiny_config()
    model = ODG(cfg).eval()
    save_checkpoint(tmp_path / "full.pt", model)
    save_checkpoint(tmp_path / "int8.pt", model, compress="int8")
    full_size, small_size = (tmp_path / "full.pt").stat().st_size, \
        (tmp_path / "int8.pt").stat().st_size
    assert small_size < 0.35 * full_size
    loaded, _ = load_model(tmp_path / "int8.pt")
    args = model_inputs(cfg)
    with torch.no_grad():
        a, b = model(*args), loaded(*args)
    assert (a.last.means - b.last.means).abs().max() < 0.5      # metres
    assert (a.last.logits - b.last.logits).abs().mean() < 0.1


def test_grown_point_head_repeats_every_point_one_voxel_grid_apart():
    small_cfg = tiny_config(points_per_layer=(1, 2, 2, 4, 4, 8))
    small = ODG(small_cfg).eval()
    big = ODG(small_cfg.replace(points_per_layer=(1, 2, 2, 4, 4, 32))).eval()
    big.load_state_dict(grow_state_dict(small.state_dict(), big))
    args = model_inputs(small_cfg)
    with torch.no_grad():
        a, b = small(*args), big(*args)
    for la, lb in zip(a.layers[:-1], b.layers[:-1]):       # earlier layers untouched
        assert torch.equal(la.means, lb.means) and torch.equal(la.logits, lb.logits)
    B, Q, K, _ = a.last.means.shape
    copies = b.last.means.reshape(B, Q, 4, K, 3)             # copy c of point k = c * K + k
    logits = b.last.logits.reshape(B, Q, 4, K, -1)
    assert torch.allclose(logits, a.last.logits.unsqueeze(2).expand_as(logits), atol=1e-5)
    shift = (copies - a.last.means.unsqueeze(2)).double()    # [B, Q, 4, K, 3]
    assert shift[..., 2].abs().max() < 1e-5                  # z unchanged
    v = small_cfg.voxel_size / 2
    expected = torch.tensor([[-v, -v], [-v, v], [v, -v], [v, v]], dtype=torch.float64)
    assert torch.allclose(shift[..., :2], expected[None, None, :, None, :].expand_as(
        shift[..., :2]), atol=1e-5)


def test_grow_state_dict_refuses_what_it_cannot_grow():
    cfg = tiny_config(points_per_layer=(1, 2, 2, 4, 4, 8))
    state = ODG(cfg).state_dict()
    with pytest.raises(ValueError, match="cannot grow 8 points per query to 12"):
        grow_state_dict(state, ODG(cfg.replace(points_per_layer=(1, 2, 2, 4, 4, 12))))
    with pytest.raises(ValueError, match="cannot grow 6 dynamic queries"):
        grow_state_dict(state, ODG(cfg.replace(num_dynamic=3)))
    with pytest.raises(ValueError, match="cannot grow 6 dynamic queries"):
        grow_state_dict(state, ODG(cfg.replace(num_dynamic=12, num_static=14)))  # same total
    with pytest.raises(ValueError, match="not a point head"):
        grow_state_dict(state, ODG(cfg.replace(embed_dims=32, fpn_channels=32,
                                                ffn_dims=64)))


def test_grown_dynamic_queries_keep_the_trained_ones_and_start_the_new_ones_fresh():
    cfg = tiny_config()                                        # 6 dynamic + 20 static
    torch.manual_seed(0)
    trained = ODG(cfg).state_dict()
    torch.manual_seed(1)
    big = ODG(cfg.replace(num_dynamic=12))
    fresh = {k: v.clone() for k, v in big.state_dict().items()}
    big.load_state_dict(grow_state_dict(trained, big))
    grown = big.state_dict()
    for key in ("queries.features", "queries.init_points"):
        assert torch.equal(grown[key][:6], trained[key][:6])          # trained dynamic
        assert torch.equal(grown[key][12:], trained[key][6:])         # trained static
        assert torch.equal(grown[key][6:12], fresh[key][6:12])        # new: as initialised
    assert torch.equal(grown["queries.init_box"][:6], trained["queries.init_box"])
    assert torch.equal(grown["queries.init_box"][6:], fresh["queries.init_box"][6:])
    assert torch.equal(grown["decoder.layers.0.points.cls.6.bias"],
                       trained["decoder.layers.0.points.cls.6.bias"])
    with torch.no_grad():
        out = big.eval()(*model_inputs(cfg))
    assert out.last.boxes.shape[1] == 12 and torch.isfinite(out.last.means).all()


def test_single_query_set_checkpoint_loads(tmp_path):
    """The ablation's one-set model (dual_queries false: no dynamic queries, num_dynamic still
    set in its config) loads as it was saved, not as a model to grow dynamic queries into."""
    cfg = tiny_config(dual_queries=False)
    model = ODG(cfg)
    save_checkpoint(tmp_path / "single.pt", model)
    loaded, loaded_cfg = load_model(tmp_path / "single.pt")
    assert not loaded_cfg.dual_queries and loaded.num_dynamic == 0
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key



def _fail_like_torch_on_a_full_disk(payload, file_name):
    with open(file_name, "wb") as f:
        f.write(b"PK" * 100)  # a partly written archive, as torch leaves one
    raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 576 vs 534")


def test_a_full_disk_is_named_and_the_previous_checkpoint_kept(tmp_path, monkeypatch):
    """torch.save reports a full disk with a message naming neither the file nor the cause;
    the save says both, leaves no temporary file, and the checkpoint written before is intact."""
    model = ODG(tiny_config())
    save_checkpoint(tmp_path / "latest.pt", model, extra={"step": 2})
    before = (tmp_path / "latest.pt").read_bytes()
    monkeypatch.setattr(checkpoint.torch, "save", _fail_like_torch_on_a_full_disk)
    monkeypatch.setattr(checkpoint.shutil, "disk_usage",
                        lambda path: shutil._ntuple_diskusage(10**9, 10**9 - 10**6, 10**6))
    with pytest.raises(OSError, match=r"no room to write the checkpoint .*latest\.pt: it needs "
                                      r"about \d+ MB, 1 MB are free") as raised:
        save_checkpoint(tmp_path / "latest.pt", model, extra={"step": 4})
    assert raised.value.errno == errno.ENOSPC
    assert sorted(p.name for p in tmp_path.iterdir()) == ["latest.pt"]
    assert (tmp_path / "latest.pt").read_bytes() == before


def test_a_failed_save_with_room_on_the_disk_keeps_its_own_error(tmp_path, monkeypatch):
    monkeypatch.setattr(checkpoint.torch, "save", _fail_like_torch_on_a_full_disk)
    with pytest.raises(RuntimeError, match="unexpected pos"):
        save_checkpoint(tmp_path / "a.pt", ODG(tiny_config()))
    assert list(tmp_path.iterdir()) == []


def test_a_really_full_disk(tmp_path):
    """The same on a real 4 MB filesystem (a tmpfs; mounting one needs root in a container
    that allows it)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4M", "tmpfs", str(disk)],
                             capture_output=True)
    if mounted.returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root and a container that allows "
                    "mounts); the monkeypatched tests above cover the message")
    try:
        with pytest.raises(OSError, match="no room to write the checkpoint") as raised:
            save_checkpoint(disk / "a.pt", ODG(tiny_config()))
        assert raised.value.errno == errno.ENOSPC
        assert list(disk.iterdir()) == []
        del raised  # its traceback holds torch's writer, the deleted file open
        gc.collect()
    finally:
        subprocess.run(["umount", "--lazy", str(disk)], check=True)


def test_unusable_checkpoints_are_one_clear_error(tmp_path):
    from odg_ros.network.checkpoint import CheckpointError, load_model
    with pytest.raises(CheckpointError, match="nope.pt not found"):
        load_model(tmp_path / "nope.pt")
    path = tmp_path / "tiny.pt"
    save_checkpoint(path, ODG(tiny_config()))
    whole = path.read_bytes()
    path.write_bytes(whole[:4096])
    with pytest.raises(CheckpointError, match="not a readable checkpoint file"):
        load_model(path)
    torch.save({"weights": 1}, path)
    with pytest.raises(CheckpointError, match="not an odg_ros checkpoint"):
        load_model(path)
    path.write_bytes(whole)
    payload = torch.load(path, weights_only=False)
    payload["config"]["no_such_option"] = 1
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match="does not fit this version.*no_such_option"):
        load_model(path)
    payload["config"].pop("no_such_option")
    payload["model"].pop(next(iter(payload["model"])))
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match="does not fit this version.*Missing key"):
        load_model(path)
