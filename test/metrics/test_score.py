"""``odg score`` end to end on a tiny Occ3D-layout split written to tmp_path, and the report
helpers of odg_ros/metrics/score.py."""
import json
import pickle

import numpy as np
import pytest

from odg_ros.commands import main
from odg_ros.classes import OCC_CLASSES, WAYMO_OCC_CLASSES
from odg_ros.metrics import MIoU, RayIoU, lidar_origins
from odg_ros.metrics.score import OccScore, format_table, resolve_occ_root

SHAPE = (200, 200, 16)


def pose(x, y=0.0, z=0.0):
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def scene_grid(rng, free, ground, thing):
    g = np.full(SHAPE, free, dtype=np.uint8)
    g[:, :, :3] = ground
    for _ in range(6):
        x, y = rng.integers(20, 180, 2)
        g[x:x + 10, y:y + 5, 3:7] = thing
    return g


def write_split(root, rng, dataset="nuscenes", with_occ_root_key=False):
    """2 scenes x 3 keyframes (the last one without GT). Returns (infos path, {token: gt})."""
    dataroot = root / "data"
    occ_dir = dataroot / ("occ" if with_occ_root_key else "gts")
    infos, gts = [], {}
    for s in range(2):
        for k in range(3):
            token = f"s{s}k{k}"
            info = {"token": token, "scene_token": f"scene{s}", "scene_name": f"scene-{s}",
                    "timestamp": 10**6 * (10 * s + k), "frame_index": k,
                    "ego_pose": pose(3.0 * k, 100.0 * s), "lidar2ego": pose(0.94, 0.0, 1.84),
                    "occ_path": ""}
            if not (s == 1 and k == 2):
                info["occ_path"] = f"scene-{s}/{token}/labels.npz"
                path = occ_dir / info["occ_path"]
                path.parent.mkdir(parents=True)
                mask = rng.random(SHAPE) < 0.7
                if dataset == "nuscenes":
                    gt = scene_grid(rng, 17, 11, 4)
                    np.savez_compressed(path, semantics=gt, mask_lidar=mask.astype(np.uint8),
                                        mask_camera=mask.astype(np.uint8))
                else:
                    gt = scene_grid(rng, 15, 13, 1)
                    np.savez_compressed(path, voxel_label=np.where(gt == 15, 23, gt),
                                        origin_voxel_state=np.ones(SHAPE, np.uint8),
                                        final_voxel_state=mask.astype(np.uint8),
                                        infov=np.ones(SHAPE, np.uint8))
                gts[token] = (gt, mask)
            infos.append(info)
    meta = {"version": "test", "dataset": dataset, "dataroot": str(dataroot), "infos": infos}
    if with_occ_root_key:
        meta["occ_root"] = "occ"
    infos_path = root / "infos.pkl"
    with open(infos_path, "wb") as f:
        pickle.dump(meta, f)
    return infos_path, gts


def write_preds(pred_dir, preds):
    pred_dir.mkdir(exist_ok=True)
    for token, pred in preds.items():
        np.savez_compressed(pred_dir / f"{token}.npz", semantics=pred.astype(np.uint8))


def run_json(capsys, *argv):
    assert main(["score", *map(str, argv), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_perfect_predictions_score_100(tmp_path, capsys):
    infos_path, gts = write_split(tmp_path, np.random.default_rng(0))
    write_preds(tmp_path / "pred", {t: g for t, (g, _) in gts.items()})
    res = run_json(capsys, "--pred", tmp_path / "pred", "--data", infos_path)
    assert set(res) >= {"mIoU", "RayIoU", "RayIoU@1", "RayIoU@2", "RayIoU@4", "per_class",
                        "IoU_geometry", "samples"}
    assert res["samples"] == 5 and res["skipped_no_gt"] == 1
    for key in ("mIoU", "RayIoU", "RayIoU@1", "RayIoU@2", "RayIoU@4", "IoU_geometry"):
        assert res[key] == pytest.approx(100.0)
    assert list(res["per_class"]) == list(OCC_CLASSES[:-1])
    assert res["per_class"]["car"]["IoU"] == pytest.approx(100.0)
    assert res["per_class"]["bus"] == {"IoU": None, "RayIoU": None, "RayIoU@1": None,
                                       "RayIoU@2": None, "RayIoU@4": None}


def test_command_equals_the_metric_classes(tmp_path, capsys):
    rng = np.random.default_rng(1)
    infos_path, gts = write_split(tmp_path, rng)
    preds = {}
    for token, (gt, _) in gts.items():
        pred = np.full_like(gt, 17)
        pred[1:] = gt[:-1]                                # shifted one voxel along x
        pred[rng.random(SHAPE) < 0.002] = 10              # and some trucks,
        pred[135:137, 90:110, 3:8] = 10                   # one in front of the LiDARs
        preds[token] = pred
    write_preds(tmp_path / "pred", preds)
    res = run_json(capsys, "--pred", tmp_path / "pred", "--data", infos_path)
    with open(infos_path, "rb") as f:
        infos = pickle.load(f)["infos"]
    miou, rayiou = MIoU(), RayIoU()
    for i, info in enumerate(infos):
        if info["occ_path"]:
            gt, mask = gts[info["token"]]
            miou.add(preds[info["token"]], gt, mask)
            rayiou.add(preds[info["token"]], gt, lidar_origins(infos, i))
    assert res["mIoU"] == pytest.approx(100 * miou.miou())
    assert res["IoU_geometry"] == pytest.approx(100 * miou.geometry_iou())
    assert res["RayIoU"] == pytest.approx(100 * rayiou.result()["RayIoU"])
    assert res["per_class"]["truck"]["IoU"] is None          # never in the GT (OPUS: NaN)
    assert res["per_class"]["truck"]["RayIoU"] == 0.0        # predicted only (SparseOcc: 0)
    assert 10 < res["mIoU"] < 95 and 10 < res["RayIoU"] < 95
    assert res["mIoU_convention"] == "sparseocc"
    # Occ3D's convention: the predicted truck counts with IoU 0, nothing else changes
    occ3d = run_json(capsys, "--pred", tmp_path / "pred", "--data", infos_path,
                     "--miou-convention", "occ3d")
    assert occ3d["mIoU_convention"] == "occ3d" and occ3d["per_class"]["truck"]["IoU"] == 0.0
    present = [c["IoU"] for c in res["per_class"].values() if c["IoU"] is not None]
    assert occ3d["mIoU"] == pytest.approx(sum(present) / (len(present) + 1))
    assert occ3d["RayIoU"] == res["RayIoU"]


def test_missing_prediction_is_an_error_naming_it(tmp_path, capsys):
    infos_path, gts = write_split(tmp_path, np.random.default_rng(2))
    preds = {t: g for t, (g, _) in gts.items() if t != "s0k1"}
    write_preds(tmp_path / "pred", preds)
    assert main(["score", "--pred", str(tmp_path / "pred"), "--data", str(infos_path)]) == 2
    err = capsys.readouterr().err
    assert "s0k1" in err and "1 of 5 predictions missing" in err


def test_bad_prediction_file_is_a_clear_error(tmp_path, capsys):
    infos_path, gts = write_split(tmp_path, np.random.default_rng(3))
    write_preds(tmp_path / "pred", {t: g for t, (g, _) in gts.items()})
    np.savez(tmp_path / "pred" / "s1k0.npz", occupancy=np.zeros(SHAPE, np.uint8))
    assert main(["score", "--pred", str(tmp_path / "pred"), "--data", str(infos_path)]) == 2
    assert "s1k0.npz: no 'semantics'" in capsys.readouterr().err
    np.savez(tmp_path / "pred" / "s1k0.npz", semantics=np.zeros((200, 200, 8), np.uint8))
    assert main(["score", "--pred", str(tmp_path / "pred"), "--data", str(infos_path)]) == 2
    assert "shape (200, 200, 8)" in capsys.readouterr().err
    np.savez(tmp_path / "pred" / "s1k0.npz", semantics=np.full(SHAPE, 255, np.uint8))
    assert main(["score", "--pred", str(tmp_path / "pred"), "--data", str(infos_path)]) == 2
    assert "outside 0..17" in capsys.readouterr().err


def test_occ_root_resolution(tmp_path, capsys):
    meta = {"dataroot": "/d"}
    assert str(resolve_occ_root(meta)) == "/d/gts"
    assert str(resolve_occ_root({**meta, "occ_root": "occ3d"})) == "/d/occ3d"
    assert str(resolve_occ_root({**meta, "occ_root": "/abs/occ"})) == "/abs/occ"
    assert str(resolve_occ_root({**meta, "occ_root": "occ3d"}, "/x")) == "/x"
    # the infos' occ_root key, and --occ-root pointing elsewhere
    infos_path, gts = write_split(tmp_path, np.random.default_rng(4), with_occ_root_key=True)
    write_preds(tmp_path / "pred", {t: g for t, (g, _) in gts.items()})
    assert run_json(capsys, "--pred", tmp_path / "pred", "--data", infos_path)["mIoU"] == 100
    (tmp_path / "data" / "occ").rename(tmp_path / "elsewhere")
    assert main(["score", "--pred", str(tmp_path / "pred"), "--data", str(infos_path)]) == 2
    assert "occupancy GT file not found" in capsys.readouterr().err
    res = run_json(capsys, "--pred", tmp_path / "pred", "--data", infos_path,
                   "--occ-root", tmp_path / "elsewhere")
    assert res["mIoU"] == 100


def test_waymo_layout(tmp_path, capsys):
    infos_path, gts = write_split(tmp_path, np.random.default_rng(5), dataset="waymo")
    preds = {}
    for token, (gt, _) in gts.items():
        pred = gt.copy()
        pred[pred == 1] = 2              # vehicles called pedestrians
        preds[token] = pred
    write_preds(tmp_path / "pred", preds)
    res = run_json(capsys, "--pred", tmp_path / "pred", "--data", infos_path)
    assert list(res["per_class"]) == list(WAYMO_OCC_CLASSES[:-1])
    assert res["per_class"]["road"]["IoU"] == pytest.approx(100.0)
    assert res["per_class"]["vehicle"]["IoU"] == 0.0
    assert res["IoU_geometry"] == pytest.approx(100.0)
    # mean over road (100) and vehicle (0); pedestrian is not in the GT
    assert res["mIoU"] == pytest.approx(50.0)


def test_table_output(tmp_path, capsys):
    infos_path, gts = write_split(tmp_path, np.random.default_rng(6))
    write_preds(tmp_path / "pred", {t: g for t, (g, _) in gts.items()})
    png = tmp_path / "scores.png"
    assert main(["score", "--pred", str(tmp_path / "pred"), "--data", str(infos_path),
                 "--png", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    out = capsys.readouterr().out
    assert "driveable_surface" in out and "RayIoU@4" in out and "MEAN" in out
    assert "geometry IoU" in out and "samples: 5" in out
    assert "mIoU convention: sparseocc" in out
    assert "keyframes without GT (not scored): 1" in out


def test_format_table_without_rayiou():
    score = OccScore(rayiou=False)
    g = np.full((4, 4, 2), 17, dtype=np.uint8)
    g[0, 0, 0] = 4
    score.add(g, g, np.ones(g.shape, dtype=bool))
    res = score.result()
    assert "RayIoU" not in res and res["mIoU"] == 100.0
    table = format_table(res)
    assert "car" in table and "100.00" in table and "RayIoU" not in table.splitlines()[0]
