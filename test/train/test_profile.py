"""odg profile train: the census of a training step, and the budget of ODG-T's step with the
CUDA paths forced (launched ops and host waits; a host wait stalls the GPU queue), with our
renderer and with gsplat's as it runs on CUDA (its kernels counted by stand-ins), at batch 1
and batch 4: the waits do not grow with the batch."""
import json

import pytest
import torch

from testing.helpers import tiny_config, write_tiny_split
from odg_ros.commands import main
from odg_ros.model_config import load_preset
from odg_ros.data.batch import collate
from odg_ros.network.backbone import ResNet
from odg_ros.bench.census import census_of_steps
from odg_ros.train.trainer import Trainer, TrainOptions

# Host waits per step, pinned where the step is (so that they can only go down), the same at
# batch 1 and 4. Our renderer: the criterion's two finiteness reads, the Hungarian cost
# matrices' one copy, and the renderer's two (one read of every size and check, one of the
# first depth batch's kept pairs with the rest's size). gsplat's: the same but its two (the
# input checks' read, and the read of its number of tile intersections).
MAX_WAITS = {"torch": 5, "gsplat": 5}
MAX_OPS = {(1, "torch"): 8_000, (4, "torch"): 13_300, (1, "gsplat"): 7_000,
           (4, "gsplat"): 12_600}


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_tiny_split(tmp_path_factory.mktemp("profile"), 3)


@pytest.fixture(scope="module")
def warm_trainer(split, tmp_path_factory):
    """ODG-T's decoder, Gaussians, losses, renderer and augmentation (on, as users train); small
    images and two frames keep the backbone cheap here (the waits depend on neither). One
    step has run: it made the optimizer's state and the device constants later steps reuse."""
    tmp_path = tmp_path_factory.mktemp("trainer")
    cfg = load_preset("odg_t", image_size=(32, 88), num_frames=2)
    weights = tmp_path / "resnet50.pth"        # random stand-ins for the pretrained weights
    torch.save(ResNet(cfg.backbone).state_dict(), weights)
    trainer = Trainer(cfg, split, TrainOptions(out_dir=tmp_path, workers=0, progress=False,
                                               device="cpu", render_pixels_per_camera=64,
                                               backbone_weights=str(weights),
                                               augment=True))
    lidar_keyframe = trainer.dataset[2]                # the one keyframe with LiDAR targets
    batches = {size: collate([lidar_keyframe] * size) for size in (1, 4)}
    census_of_steps(trainer, [batches[1]], cuda_paths=True, warm_up=True)   # the warm-up only
    return trainer, batches


@pytest.mark.parametrize("renderer", ["torch", "gsplat"])
def test_odg_t_training_step_waits_do_not_grow_with_the_batch(warm_trainer, renderer):
    trainer, batches = warm_trainer
    waits = {}
    for size, batch in batches.items():
        census = census_of_steps(trainer, [batch], cuda_paths=True, renderer=renderer,
                                 warm_up=False)
        report = f"batch {size}, {renderer}:\n{census.report()}"
        print(report)                                        # pytest -rP shows them
        assert census.per_step(census.ops, "render") > 100, report        # the renderer ran
        assert census.per_step(census.ops, "data") > 30 * size, report    # the augmentation
        assert census.waits_by_kind()["upload"] == 0, report
        assert census.per_step(census.ops) <= MAX_OPS[(size, renderer)], report
        waits[size] = census.per_step(census.syncs)
        assert waits[size] <= MAX_WAITS[renderer], report
    assert waits[4] == waits[1]


def test_profile_command_prints_phases_and_lines(split, tmp_path, capsys):
    preset = tmp_path / "tiny.yaml"
    preset.write_text(json.dumps({k: list(v) if isinstance(v, tuple) else v     # JSON is YAML
                                  for k, v in tiny_config(num_frames=2).to_dict().items()}))
    out = tmp_path / "census.json"
    assert main(["profile", "train", "--preset", str(preset), "--data", str(split),
                 "--cuda-paths", "--renderer", "gsplat", "--top", "3", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "renderer gsplat, CUDA paths forced" in text
    for phase in ("forward", "losses", "backward", "optimizer", "total"):
        assert f"\n{phase}" in text
    assert "host waits per step by kind: read" in text
    saved = json.loads(out.read_text())
    assert saved["ops_per_step"] > 0 and len(saved["ops_by_line"]) == 3
    assert sum(p["ops"] for p in saved["by_phase"].values()) == saved["ops_per_step"]
    assert saved["by_phase"]["backward"]["ops"] > 0 and saved["gpu"] is None
    assert set(saved["waits_by_kind"]) == {"read", "download", "shape", "upload"}
    assert saved["renderer"] == "gsplat" and saved["waits_by_kind"]["read"] >= 2
    assert main(["profile", "train", "--data", str(tmp_path / "missing.pkl")]) == 2


def test_renderer_waits_grow_with_neither_batch_nor_image(warm_trainer, split, tmp_path,
                                                          monkeypatch):
    """At the size users train (256 x 704, batch 4) the candidate pairs far outnumber the
    first depth batch; here the first batch is made that small against these sizes' pairs
    (FIRST_BATCH_SHARE 0, 2,000 candidates) and the rest's chunks too, so every step needs
    several chunks. The rest is sized in the first batch's read and its chunks read nothing:
    the waits are the same at batch 1 and 4 and at 32 x 88 and 64 x 176, and as with one
    batch (with a read per batch, as before, they grew)."""
    from odg_ros.render import splat
    monkeypatch.setattr(splat, "FIRST_BATCH_SHARE", 0.0)
    monkeypatch.setattr(splat, "CANDIDATE_CHUNK", 2_000)
    monkeypatch.setattr(splat, "LATER_CANDIDATE_CHUNK", 2_000)
    batches = []
    candidate_pairs = splat._candidate_pairs
    monkeypatch.setattr(splat, "_candidate_pairs",
                        lambda *args: batches.append(1) or candidate_pairs(*args))
    trainer, by_size = warm_trainer
    larger = Trainer(load_preset("odg_t", image_size=(64, 176), num_frames=2), split,
                     TrainOptions(out_dir=tmp_path, workers=0, progress=False, device="cpu",
                                  render_pixels_per_camera=64,
                                  backbone_weights=trainer.opts.backbone_weights, augment=True))
    lidar_batch = collate([larger.dataset[2]])
    census_of_steps(larger, [lidar_batch], cuda_paths=True, warm_up=True)   # the warm-up
    waits = {}
    for name, (t, batch) in {"32 x 88, batch 1": (trainer, by_size[1]),
                             "32 x 88, batch 4": (trainer, by_size[4]),
                             "64 x 176, batch 1": (larger, lidar_batch)}.items():
        batches.clear()
        census = census_of_steps(t, [batch], cuda_paths=True, warm_up=False)
        assert len(batches) >= 3, (name, len(batches))      # the rest in several chunks
        waits[name] = census.per_step(census.syncs)
    assert set(waits.values()) == {MAX_WAITS["torch"]}, waits
