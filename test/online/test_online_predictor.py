"""The streaming predictor (backbone once per set, cached history) equals the offline model
run over the same frames with every frame's features recomputed."""
import numpy as np
import pytest
import torch
from testing.helpers import assert_layers_close, published_grid

from odg_ros.geometry import ego_warp
from odg_ros.online.predictor import OnlinePredictor
from odg_ros.preprocess import normalize
from testing.online import make_model, make_sets, raw_output, stepped_predictor


def offline(model, sets, index, num_frames):
    """model.forward over frames index, index-1, ... (newest first), all recomputed."""
    chosen = [sets[i] for i in range(index, max(-1, index - num_frames), -1)]
    current_pose, current_stamp = chosen[0][2], chosen[0][3]
    images = torch.stack([normalize(torch.from_numpy(s[0])) for s in chosen])[None]
    ego2img = torch.tensor(np.stack([s[1] for s in chosen]), dtype=torch.float32)[None]
    warps = torch.tensor(np.stack([ego_warp(current_pose, s[2]) for s in chosen]),
                         dtype=torch.float32)[None]
    deltas = torch.tensor([current_stamp - s[3] for s in chosen], dtype=torch.float32)[None]
    with torch.inference_mode():
        return model(images, ego2img, warps, deltas)


def test_online_equals_offline_over_a_sequence():
    model, cfg = make_model()
    sets = make_sets(cfg, 4)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0)
    from odg_ros.network.postprocess import box_list
    for i, s in enumerate(sets):
        online = predictor.step(*s)
        assert online.num_frames == min(i + 1, cfg.num_frames)
        reference = offline(model, sets, i, cfg.num_frames)
        assert_layers_close(raw_output(predictor).layers, reference.layers, 1e-4)
        grid, confidence = published_grid(reference, cfg)
        occupied = (online.grid != 17).sum()
        assert occupied > 50                                     # a real comparison
        agree = (online.grid == grid[0].numpy()).mean()
        assert agree == 1.0, f"labels differ in {(1 - agree) * online.grid.size:.0f} voxels"
        assert np.abs(online.confidence.astype(int) - confidence[0].numpy()).max() <= 1
        boxes = box_list(reference, cfg)[0]
        assert len(online.boxes) == len(boxes) == cfg.num_dynamic
        for a, b in zip(online.boxes, boxes):
            assert a["class_name"] == b["class_name"]
            assert np.allclose(a["center"], b["center"], atol=1e-3)
        assert set(online.timings) == {"upload", "model", "download"}
        assert all(t >= 0 for t in online.timings.values())


def test_history_reset_on_time_jump_gives_a_single_frame():
    predictor, model, cfg, sets = stepped_predictor(3)
    # a set from the past (the bag looped): the decoder must see only that set
    looped = predictor.step(*sets[0])
    assert looped.num_frames == 1 and looped.history_reset == "time_backwards"
    reference = offline(model, sets, 0, 1)
    torch.testing.assert_close(raw_output(predictor).last.means, reference.last.means,
                               atol=1e-4, rtol=1e-4)
    # a gap longer than max_gap
    images, ego2img, pose, stamp = sets[1]
    gap = predictor.step(images, ego2img, pose, sets[0][3] + 5.0)
    assert gap.num_frames == 1 and gap.history_reset == "gap"


def test_rejects_wrong_image_shape():
    model, cfg = make_model()
    predictor = OnlinePredictor(model, cfg, "cpu")
    images, ego2img, pose, stamp = make_sets(cfg, 1)[0]
    with pytest.raises(ValueError, match="expected"):
        predictor.step(images[:, :32], ego2img, pose, stamp)


def test_history_keeps_frames_spaced_like_training_whatever_the_camera_rate():
    """Sets every 0.5 s in make_sets; with min_interval 0.9 s the kept history frames are
    >= 0.9 s apart (every other set), the current set is always frame 0 (it replaces a
    provisional predecessor), and the result equals the offline model over those frames."""
    model, cfg = make_model()
    sets = make_sets(cfg, 6)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0,
                                min_interval=0.9)
    kept_stamps = []
    for i, s in enumerate(sets):
        online = predictor.step(*s)
        kept_stamps.append([f.stamp for f in predictor.history.frames()])
    assert kept_stamps[2] == [11.0, 10.0]         # set 1 was provisional, replaced by set 2
    assert kept_stamps[4] == [12.0, 11.0, 10.0]   # set 3 provisional, replaced by set 4
    assert kept_stamps[-1] == [12.5, 12.0, 11.0]  # set 5 current (provisional), 4, 2 kept
    chosen = [sets[2], sets[4], sets[5]]           # oldest first, as offline() indexes
    reference = offline(model, chosen, 2, 3)
    torch.testing.assert_close(raw_output(predictor).last.means, reference.last.means,
                               atol=1e-4, rtol=1e-4)


def test_bf16_predictor_stays_close_to_fp32_and_unknown_precision_fails():
    """bf16 autocast on CPU: geometry stays float32 (sampling.full_precision), so the means
    move by bf16 feature rounding only; the grid keeps almost every label."""
    model, cfg = make_model()
    sets = make_sets(cfg, 3)
    full = OnlinePredictor(model, cfg, "cpu")
    half = OnlinePredictor(model, cfg, "cpu", precision="bf16")
    for s in sets:
        a, b = full.step(*s), half.step(*s)
        means_a, means_b = raw_output(full).last.means, raw_output(half).last.means
        assert means_b.dtype == torch.float32 and torch.isfinite(means_b).all()
        assert (means_a - means_b).abs().max() < 0.05          # metres (measured ~0.005)
        assert (means_a - means_b).abs().mean() < 0.01
        occupied = (a.grid != 17) | (b.grid != 17)
        assert (a.grid[occupied] == b.grid[occupied]).mean() > 0.8
    with pytest.raises(ValueError, match="precision"):
        OnlinePredictor(model, cfg, "cpu", precision="fp8")
    with pytest.raises(ValueError, match="CUDA"):
        OnlinePredictor(model, cfg, "cpu", precision="fp16")


def test_precision_auto_is_bf16_only_where_the_cpu_has_bf16_instructions(monkeypatch):
    """auto: the bf16 encoder on a CPU with AVX512-BF16 or AMX (and oneDNN's bf16 kernels),
    fp32 on one without (oneDNN also says yes on a plain AVX-512 CPU, where bf16 is
    emulated) and on a GPU; an explicit precision is kept."""
    from odg_ros.network import precision

    model, cfg = make_model()
    monkeypatch.setattr(precision, "_cpu_flags", lambda: frozenset({"avx2", "avx512f"}))
    assert not precision.cpu_has_native_bf16()
    assert OnlinePredictor(model, cfg, "cpu", precision="auto").precision == "fp32"
    assert OnlinePredictor(model, cfg, "cpu", precision="bf16").precision == "bf16"
    monkeypatch.setattr(precision, "_cpu_flags", lambda: frozenset({"avx512f", "avx512_bf16"}))
    native = precision.cpu_has_native_bf16()
    assert native == bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    assert precision.resolve_precision("auto", "cpu") == ("bf16-encoder" if native else "fp32")
    assert precision.resolve_precision("auto", "cuda") == "fp32"
    with pytest.raises(ValueError, match="precision"):
        precision.resolve_precision("fp8", "cpu")


@pytest.mark.parametrize("precision", ["fp32", "bf16", "bf16-encoder"])
def test_the_evaluation_model_computes_what_the_node_step_computes(precision):
    """``odg eval --precision``'s model (every frame through the step's own backbone, then
    the decoder) gives the online step's outputs on the same frames."""
    from odg_ros.online.step import NodeInferenceModel

    model, cfg = make_model()
    sets = make_sets(cfg, 3)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, precision=precision)
    evaluated = NodeInferenceModel(model, cfg, "cpu", precision)
    for i, s in enumerate(sets):
        predictor.step(*s)
        chosen = [sets[j] for j in range(i, max(-1, i - cfg.num_frames), -1)]
        pose, stamp = chosen[0][2], chosen[0][3]
        with torch.inference_mode():
            output = evaluated(
                torch.stack([normalize(torch.from_numpy(c[0])) for c in chosen])[None],
                torch.tensor(np.stack([c[1] for c in chosen]), dtype=torch.float32)[None],
                torch.tensor(np.stack([ego_warp(pose, c[2]) for c in chosen]),
                             dtype=torch.float32)[None],
                torch.tensor([stamp - c[3] for c in chosen], dtype=torch.float32)[None])
        assert_layers_close(raw_output(predictor).layers, output.layers, 1e-4)
