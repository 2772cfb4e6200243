"""odg prepare on a tiny synthetic world: the infos agree with what the generator placed
(poses at every camera's stamp, intrinsics, sweeps, boxes and velocities in the ego frame)."""
import functools
import json
import os
import pickle
import shutil

import numpy as np
import pytest

from odg_ros.classes import BOX_CLASSES
from odg_ros.commands import main as cli_main
from odg_ros.nuscenes_cameras import CAMERA_NAMES
from odg_ros.data.nuscenes_tables import CATEGORY_TO_BOX_CLASS
from odg_ros.data.prepare import build_infos, load_infos, save_infos
from odg_ros.data.synth import sensor_rig
from odg_ros.data.synth.generate import camera_time, generate, keyframe_time, scene_world
from odg_ros.geometry import invert_transform, is_rigid

SEED, SECONDS, HW = 23, 1.5, (45, 80)


@functools.lru_cache(maxsize=None)
def world_of(scene_name):
    return scene_world(SEED, int(scene_name[-4:]) - 1, SECONDS)


@pytest.fixture(scope="module")
def world_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth_prepare")
    generate(str(out), scenes=2, seconds=SECONDS, seed=SEED, image_hw=HW, progress=False)
    return out


@pytest.fixture(scope="module")
def infos(world_dir):
    return build_infos(world_dir, split="all", progress=False)


def test_top_level_and_order(infos, world_dir):
    assert infos["dataset"] == "nuscenes" and infos["version"] == "v1.0-trainval"
    assert infos["dataroot"] == str(world_dir) and infos["occ_root"] == "gts"
    items = infos["infos"]
    assert len(items) == 6
    assert [i["scene_name"] for i in items] == ["scene-0001"] * 3 + ["scene-0002"] * 3
    assert [i["frame_index"] for i in items] == [0, 1, 2] * 2
    for a, b in zip(items[:-1], items[1:]):
        if a["scene_token"] == b["scene_token"]:
            assert b["timestamp"] - a["timestamp"] == 500_000


def test_splits_follow_splits_json(world_dir):
    train = build_infos(world_dir, split="train", progress=False)["infos"]
    val = build_infos(world_dir, split="val", progress=False)["infos"]
    assert {i["scene_name"] for i in train} == {"scene-0001"} and {i["scene_name"] for i in val} == {"scene-0002"}
    with pytest.raises(ValueError):
        build_infos(world_dir, split="mini_train", progress=False)


def test_official_splits_without_splits_json(world_dir, tmp_path):
    pytest.importorskip("nuscenes", reason="nuscenes-devkit not installed")
    copy = tmp_path / "root"
    shutil.copytree(world_dir / "v1.0-trainval", copy / "v1.0-trainval")
    # scene-0001 and scene-0002 are in the official nuScenes train split
    names = {i["scene_name"] for i in build_infos(copy, split="train", progress=False)["infos"]}
    assert names == {"scene-0001", "scene-0002"}
    assert build_infos(copy, split="val", progress=False)["infos"] == []


def test_poses_intrinsics_and_paths_match_the_generator(infos, world_dir):
    cams = sensor_rig.cameras(HW)
    for info in infos["infos"]:
        world = world_of(info["scene_name"])
        k = info["frame_index"]
        assert np.allclose(info["ego_pose"], world.ego_pose(keyframe_time(k)))
        assert np.allclose(info["lidar2ego"], sensor_rig.lidar_T_ego_from_lidar())
        assert os.path.exists(os.path.join(world_dir, info["lidar_path"]))
        assert os.path.exists(os.path.join(world_dir, info["lidarseg_path"]))
        assert os.path.exists(os.path.join(world_dir, "gts", info["occ_path"]))
        assert list(info["cams"]) == list(CAMERA_NAMES)
        for cam in cams:
            c = info["cams"][cam.name]
            t = camera_time(6 * k, cam.name)
            assert c["image_hw"] == HW and os.path.exists(os.path.join(world_dir, c["data_path"]))
            assert np.allclose(c["intrinsics"], cam.intrinsics)
            assert np.allclose(c["sensor2ego"], cam.T_ego_from_cam) and is_rigid(c["sensor2ego"])
            assert np.allclose(c["ego_pose"], world.ego_pose(t))
            assert c["timestamp"] - info["timestamp"] == round((t - keyframe_time(k)) * 1e6)


def test_sweeps_are_the_earlier_sets_newest_first(infos):
    for info in infos["infos"]:
        sweeps = info["sweeps"]
        assert len(sweeps) == (0 if info["frame_index"] == 0 else 5)
        last = info["cams"]["CAM_FRONT"]["timestamp"]
        for s in sweeps:
            assert list(s) == list(CAMERA_NAMES)
            stamps = [s[c]["timestamp"] for c in CAMERA_NAMES]
            assert max(stamps) - min(stamps) < 50_000
            assert s["CAM_FRONT"]["timestamp"] == pytest.approx(last - 1e6 / 12, abs=1)
            assert "sweeps/" in s["CAM_FRONT"]["data_path"]
            last = s["CAM_FRONT"]["timestamp"]


def test_boxes_match_the_world(infos, world_dir):
    total = 0
    for info in infos["infos"]:
        world = world_of(info["scene_name"])
        t = keyframe_time(info["frame_index"])
        centre, yaw, wlh, vel = world.boxes(t)
        T_eg = invert_transform(world.ego_pose(t))
        centre_e = centre @ T_eg[:3, :3].T + T_eg[:3, 3]
        ego_yaw = np.arctan2(T_eg[1, 0], T_eg[0, 0])
        boxes, labels = info["gt_boxes"], info["gt_labels"]
        assert boxes.shape == (len(labels), 9) and labels.dtype == np.int64 and np.isfinite(boxes).all()
        for box, label in zip(boxes, labels):
            i = int(np.argmin(np.linalg.norm(centre_e - box[:3], axis=1)))
            assert np.allclose(centre_e[i], box[:3], atol=1e-6)
            assert np.allclose(wlh[i], box[3:6])
            dyaw = (box[6] - (yaw[i] + ego_yaw) + np.pi) % (2 * np.pi) - np.pi
            assert abs(dyaw) < 1e-6
            category = world.things[i].shape.category
            assert BOX_CLASSES[label] == CATEGORY_TO_BOX_CLASS[category]
            if info["frame_index"] == 1:  # centred difference: exact for these motions up to ~accel * dt
                v_true = T_eg[:2, :2] @ vel[i]
                assert np.linalg.norm(box[7:9] - v_true) < 0.5
        total += len(labels)
    assert total > 20


def test_non_box_categories_and_empty_boxes_are_skipped(infos, world_dir):
    from odg_ros.data.nuscenes_tables import NuScenesTables
    tables = NuScenesTables(world_dir)
    skipped_category = skipped_empty = 0
    for info in infos["infos"]:
        anns = tables.annotations[info["token"]]
        boxed = [a for a in anns if CATEGORY_TO_BOX_CLASS.get(tables.category_name(a))]
        skipped_category += len(anns) - len(boxed)
        skipped_empty += sum(a["num_lidar_pts"] == 0 for a in boxed)
        assert len(info["gt_labels"]) == sum(a["num_lidar_pts"] > 0 for a in boxed)
    assert skipped_category > 0 and skipped_empty > 0  # trash bins / bike racks; occluded objects


def test_save_load_roundtrip_and_cli(infos, world_dir, tmp_path):
    path = tmp_path / "infos.pkl"
    save_infos(infos, path)
    again = load_infos(path)
    assert again["infos"][3]["token"] == infos["infos"][3]["token"]
    with open(tmp_path / "foreign.pkl", "wb") as f:
        pickle.dump([1, 2, 3], f)
    with pytest.raises(ValueError):
        load_infos(tmp_path / "foreign.pkl")
    out = tmp_path / "cli.pkl"
    assert cli_main(["prepare", "--dataroot", str(world_dir), "--out", str(out), "--split", "val"]) == 0
    assert len(load_infos(out)["infos"]) == 3


def test_dataset_reads_the_infos(infos):
    """The OccDataset (data/dataset.py) turns these infos into model-ready samples."""
    from odg_ros.model_config import load_preset
    from odg_ros.data.dataset import OccDataset
    ds = OccDataset(infos, load_preset("odg_cpu"))
    sample = ds[2]
    assert sample["images"].shape[1:] == (6, 128, 352, 3)
    assert sample["occ_mask_camera"].any() and (sample["occ_semantics"] != 17).any()
    assert sum(len(t) for t in sample["render_targets"]) > 100


def test_missing_tables_give_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no nuScenes tables"):
        build_infos(tmp_path, progress=False)


def test_prepare_refuses_a_bogus_or_empty_split(world_dir, tmp_path, capsys):
    out = tmp_path / "infos.pkl"
    assert cli_main(["prepare", "--dataroot", str(world_dir), "--out", str(out),
                     "--split", "bogus"]) == 2
    assert "split 'bogus' not in" in capsys.readouterr().err
    # a world without val scenes: its tables, and a splits.json with an empty val
    no_val = tmp_path / "no_val"
    no_val.mkdir()
    (no_val / "v1.0-trainval").symlink_to(world_dir / "v1.0-trainval")
    splits = json.loads((world_dir / "splits.json").read_text())
    (no_val / "splits.json").write_text(json.dumps({"train": splits["train"], "val": []}))
    assert cli_main(["prepare", "--dataroot", str(no_val), "--out", str(out),
                     "--split", "val"]) == 2
    assert "split 'val' of" in capsys.readouterr().err and not out.exists()
