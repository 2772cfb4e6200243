"""odg profile train: the census of a training step, and the budget of ODG-T's step with the
CUDA paths forced (launched ops and host syncs; a host sync stalls the GPU queue)."""
import json

import pytest
import torch

from testing.helpers import tiny_config, write_tiny_split
from odg_ros.commands import main
from odg_ros.config import load_preset
from odg_ros.data.batch import collate
from odg_ros.network.backbone import ResNet
from odg_ros.train.census import census_of_steps
from odg_ros.train.trainer import Trainer, TrainOptions

MAX_OPS = 12_000
# Outside the renderer: the criterion's two finiteness reads and the Hungarian cost matrices'
# one copy. The augmentation and the GT checks wait for nothing (the targets stay on the host).
MAX_SYNCS_OUTSIDE_RENDERER = 3
# One renderer call draws all six layers. It still waits for the device to size its work:
# the projection's candidates, one read of every size and check before compositing, and one
# compaction per depth batch (one batch here). Pinned where it is, so that it can only go down.
MAX_SYNCS = 6


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_tiny_split(tmp_path_factory.mktemp("profile"), 3)


def test_odg_t_training_step_stays_within_its_budget(split, tmp_path):
    # ODG-T's decoder, Gaussians, losses, renderer and augmentation (on, as users train); small
    # images and two frames keep the backbone cheap here (the host syncs depend on neither)
    cfg = load_preset("odg_t", image_size=(32, 88), num_frames=2)
    weights = tmp_path / "resnet50.pth"        # random stand-ins for the pretrained weights
    torch.save(ResNet(cfg.backbone).state_dict(), weights)
    trainer = Trainer(cfg, split, TrainOptions(out_dir=tmp_path, workers=0, progress=False,
                                               device="cpu", render_pixels_per_camera=64,
                                               backbone_weights=str(weights),
                                               augment=True))
    lidar_keyframe = collate([trainer.dataset[2]])     # the one keyframe with LiDAR targets
    census = census_of_steps(trainer, [lidar_keyframe] * 2, cuda_paths=True)
    report = census.report()
    assert census.per_step(census.ops, "render") > 100, report        # the renderer ran
    assert census.per_step(census.ops, "data") > 30, report           # and the augmentation
    outside_renderer = sum(n for (phase, line), n in census.syncs.items()
                           if phase != "render" and not line.startswith("render/"))
    assert outside_renderer / census.steps <= MAX_SYNCS_OUTSIDE_RENDERER, report
    assert census.per_step(census.syncs) <= MAX_SYNCS, report
    assert census.per_step(census.ops) <= MAX_OPS, report


def test_profile_command_prints_phases_and_lines(split, tmp_path, capsys):
    preset = tmp_path / "tiny.yaml"
    preset.write_text(json.dumps({k: list(v) if isinstance(v, tuple) else v     # JSON is YAML
                                  for k, v in tiny_config(num_frames=2).to_dict().items()}))
    out = tmp_path / "census.json"
    assert main(["profile", "train", "--preset", str(preset), "--data", str(split),
                 "--cuda-paths", "--top", "3", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    for phase in ("forward", "losses", "backward", "optimizer", "total"):
        assert f"\n{phase}" in text
    saved = json.loads(out.read_text())
    assert saved["ops_per_step"] > 0 and len(saved["ops_by_line"]) == 3
    assert sum(p["ops"] for p in saved["by_phase"].values()) == saved["ops_per_step"]
    assert saved["by_phase"]["backward"]["ops"] > 0 and saved["gpu"] is None
    assert main(["profile", "train", "--data", str(tmp_path / "missing.pkl")]) == 2
