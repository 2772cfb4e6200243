"""Occ3D-Waymo end to end: the synthetic world in the Waymo layout, odg prepare --layout waymo,
train -> eval -> score with the Waymo label set (15 classes, 15 = free)."""
import json

import numpy as np
import pytest
import torch
import yaml

from odg_ros.classes import WAYMO_OCC_CLASSES
from odg_ros.commands import main as cli_main
from odg_ros.model_config import load_preset
from odg_ros.data.dataset import OccDataset
from odg_ros.data.prepare import build_infos
from odg_ros.data.prepare_waymo import (WAYMO_CAMERA_NAMES, build_waymo_infos, opencv_sensor2ego,
                                        WAYMO_FROM_OPENCV_CAMERA)
from odg_ros.data.synth.generate import generate
from odg_ros.data.synth.waymo_layout import NUSCENES_TO_WAYMO_FILE, write_waymo_layout

TINY = dict(backbone="resnet18", image_size=[64, 112], num_frames=2, embed_dims=32,
            fpn_channels=32, ffn_dims=64, num_heads=4, num_static=20, num_dynamic=6,
            points_per_layer=[1, 2, 2, 4, 4, 8], num_groups=4, sampling_points=2,
            mixing_out_points=8)
# nuScenes camera index of each Waymo camera (synth/waymo_layout.SOURCE_CAMERA)
NUSCENES_INDEX = [0, 2, 1, 4, 5]


def test_synth_prepare_train_eval_score(tmp_path, capsys):
    root, run = tmp_path / "waymo", tmp_path / "run"
    assert cli_main(["synth", "--layout", "waymo", "--out", str(root), "--scenes", "2",
                     "--seconds", "1", "--seed", "3", "--image-size", "64", "112"]) == 0
    for split in ("train", "val"):
        assert cli_main(["prepare", "--layout", "waymo", "--frame-hz", "2", "--dataroot",
                         str(root), "--split", split, "--out", str(root / f"{split}.pkl")]) == 0
    preset = load_preset("odg_waymo_cpu", **TINY).to_dict()
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(
        {k: list(v) if isinstance(v, tuple) else v for k, v in preset.items()}))
    capsys.readouterr()
    assert cli_main(["train", "--preset", str(tmp_path / "tiny.yaml"), "--data",
                     str(root / "train.pkl"), "--out", str(run), "--steps", "2", "--workers", "0",
                     "--warmup", "1", "--device", "cpu"]) == 0
    capsys.readouterr()
    assert cli_main(["eval", "--checkpoint", str(run / "final.pt"), "--data",
                     str(root / "val.pkl"), "--save-pred", str(tmp_path / "pred"), "--device",
                     "cpu", "--json"]) == 0
    evaluated = json.loads(capsys.readouterr().out)
    assert list(evaluated["per_class"]) == list(WAYMO_OCC_CLASSES[:-1])
    grids = [np.load(p)["semantics"] for p in sorted((tmp_path / "pred").glob("*.npz"))]
    assert len(grids) == 2 and all(g.max() <= 15 and (g == 15).any() for g in grids)
    # unpadded, the grid reaches the metrics as post-processing made it (free must be 15)
    assert cli_main(["eval", "--checkpoint", str(run / "final.pt"), "--data",
                     str(root / "val.pkl"), "--device", "cpu", "--json", "--no-rayiou",
                     "--limit", "1", "--set", "occupancy_padding=false"]) == 0
    capsys.readouterr()
    assert cli_main(["score", "--pred", str(tmp_path / "pred"), "--data", str(root / "val.pkl"),
                     "--json"]) == 0
    scored = json.loads(capsys.readouterr().out)
    assert list(scored["per_class"]) == list(WAYMO_OCC_CLASSES[:-1])
    assert scored["mIoU"] == evaluated["mIoU"]


def test_waymo_layout_keeps_images_geometry_and_labels(tmp_path):
    """The same keyframe through both layouts: the five cameras' pixels and projections, the
    GT mapped to the Waymo labels, the camera mask cut to the five cameras' view."""
    generate(str(tmp_path / "nus"), scenes=1, seconds=0.5, seed=4, image_hw=(48, 88),
             progress=False)
    nus_infos = build_infos(tmp_path / "nus", split="all", progress=False)
    write_waymo_layout(nus_infos, str(tmp_path / "waymo"))
    waymo_infos, notes = build_waymo_infos(tmp_path / "waymo", split="train", frame_hz=2)
    assert notes == [] and waymo_infos["dataset"] == "waymo"
    assert tuple(waymo_infos["infos"][0]["cams"]) == WAYMO_CAMERA_NAMES
    small = dict(backbone="resnet18", image_size=(48, 88), num_frames=1)
    nus = OccDataset(nus_infos, load_preset("odg_cpu", **small))[0]
    way = OccDataset(waymo_infos, load_preset("odg_waymo_cpu", **small))[0]
    torch.testing.assert_close(way["images"], nus["images"][:, NUSCENES_INDEX])
    torch.testing.assert_close(way["ego2img"], nus["ego2img"][:, NUSCENES_INDEX],
                               rtol=1e-5, atol=1e-3)
    expected = NUSCENES_TO_WAYMO_FILE[nus["occ_semantics"].numpy()]
    expected[expected == 23] = 15
    np.testing.assert_array_equal(way["occ_semantics"].numpy(), expected)
    mask_nus, mask_way = nus["occ_mask_camera"].numpy(), way["occ_mask_camera"].numpy()
    assert not (mask_way & ~mask_nus).any()
    behind = mask_nus[:60, 90:110].sum()      # seen by CAM_BACK only: not by Waymo's cameras
    assert behind > 0 and mask_way[:60, 90:110].sum() < 0.05 * behind


def test_sensor2ego_in_waymo_camera_axes_is_converted():
    # a front camera 1.5 m up; in Waymo's camera axes (x forward) its rotation is the identity
    waymo_axes = np.eye(4)
    waymo_axes[:3, 3] = (1.5, 0.0, 1.5)
    converted, was = opencv_sensor2ego(waymo_axes)
    assert was
    # OpenCV: optical axis z -> ego +x, image right x -> ego -y, image down y -> ego -z
    np.testing.assert_allclose(converted[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    np.testing.assert_allclose(converted[:3, 3], waymo_axes[:3, 3])
    same, was = opencv_sensor2ego(converted)
    assert not was and same is converted
    np.testing.assert_allclose(WAYMO_FROM_OPENCV_CAMERA[:3, :3] @ WAYMO_FROM_OPENCV_CAMERA[:3, :3].T,
                               np.eye(3))


def test_prepare_refuses_mismatched_pose_and_image(tmp_path):
    import pickle
    generate(str(tmp_path / "nus"), scenes=1, seconds=0.5, seed=4, image_hw=(48, 88),
             progress=False)
    write_waymo_layout(build_infos(tmp_path / "nus", split="all", progress=False),
                       str(tmp_path / "waymo"))
    path = tmp_path / "waymo" / "cam_infos.pkl"
    poses = pickle.loads(path.read_bytes())
    poses[0][0][1]["intrinsics"] = np.array([[50.0, 0, 44], [0, 50, 300], [0, 0, 1]])
    path.write_bytes(pickle.dumps(poses))
    with pytest.raises(ValueError, match="principal point .* outside"):
        build_waymo_infos(tmp_path / "waymo", split="train", frame_hz=2)
    del poses[0][0][1]["intrinsics"]
    path.write_bytes(pickle.dumps(poses))
    with pytest.raises(ValueError, match=r"camera 1: the pose file lacks \['intrinsics'\]"):
        build_waymo_infos(tmp_path / "waymo", split="train", frame_hz=2)
