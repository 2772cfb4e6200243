"""odg demo end to end, small: a 1.5 s synthetic scene at 72 x 128, a tiny random-weights
checkpoint, the node and the replay in their own processes over loopback DDS, this test
reading the JSON the command prints. Also the ROS-free pieces the numbers are made of."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from odg_ros.demo import DemoError
from odg_ros.demo.picture import UNKNOWN_COLOR, bev_rgb, unknown_columns
from odg_ros.demo.records import CameraSets, ReceivedGrid, SessionRecord, bag_camera_sets
from odg_ros.demo.report import (format_summary, grid_latencies_ms, keyframes_by_stamp,
                                 score_keyframes, summarize_session)
from odg_ros.demo.demo_world import WorldSpec, build_demo_world, resolve_checkpoint, world_is_built
from odg_ros.classes import OCC_CLASSES
from testing.helpers import write_tiny_checkpoint

REPORT_KEYS = ("frames_in", "frames_out", "dropped", "fps", "latency_ms_p50", "latency_ms_p95",
               "mIoU", "RayIoU")


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    return write_tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt")


def run_demo(out, checkpoint, *extra, timeout=240):
    return subprocess.run(
        [sys.executable, "-m", "odg_ros.commands", "demo", "--out", str(out), "--checkpoint",
         str(checkpoint), "--seconds", "1.5", "--image-size", "72", "128", "--rate", "0.5",
         *extra], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def demo_run(tiny_checkpoint, tmp_path_factory):
    pytest.importorskip("rclpy", reason="the ROS 2 Python wheels are not usable (make setup)")
    out = tmp_path_factory.mktemp("demo") / "out"
    result = run_demo(out, tiny_checkpoint, "--json", "--device", "cpu")
    assert result.returncode == 0, result.stderr[-3000:]
    return out, result


def test_demo_runs_the_whole_path_across_processes(demo_run):
    out, result = demo_run
    report = json.loads(result.stdout)                 # --json: nothing but the JSON
    for key in REPORT_KEYS:
        assert key in report, key
    assert report["frames_in"] == 13                   # 1.5 s of 12 Hz camera sets
    assert 0 < report["frames_out"] <= report["frames_in"]
    # every set is accounted for: an output, or a drop the node counted (a set whose every
    # image was lost on the way, best effort, would be 'unaccounted'; at most the first one,
    # sent while the node's readers were still matching the replay's writers)
    assert report["lost_in_transport"] == 0
    assert report["unaccounted"] in (0, 1), report
    assert report["frames_out"] + report["dropped"] + report["unaccounted"] == report["frames_in"]
    assert report["keyframes"] == 3 and report["keyframes_scored"] > 0
    assert report["device"] == "cpu" and ") on cpu" in (out / "node.log").read_text()
    assert 0.0 <= report["mIoU"] <= 100.0 and 0.0 <= report["RayIoU"] <= 100.0
    assert report["fps"] > 0 and 0 < report["latency_ms_p50"] <= report["latency_ms_p95"]
    assert report["latency_samples"] == report["frames_out"]
    assert list(report["per_class"]) == list(OCC_CLASSES[:-1])
    assert json.loads((out / "demo.json").read_text())["frames_out"] == report["frames_out"]
    with Image.open(out / "demo.png") as picture:
        assert picture.width > 600 and picture.height > 600
        # the prediction's unknown space is drawn in its own colour
        pixels = np.asarray(picture.convert("RGB")).reshape(-1, 3)
        assert (pixels == UNKNOWN_COLOR).all(axis=1).sum() > 1000
    assert "Traceback" not in (out / "node.log").read_text()
    assert "reusing" not in result.stderr and "building the demo world" in result.stderr


def test_grids_are_matched_to_their_keyframes_by_stamp(demo_run):
    """The GT itself, received under its keyframe's CAM_FRONT stamp, scores 100; under the
    neighbouring keyframe's stamp it does not."""
    from odg_ros.data.occ_io import load_occ
    from odg_ros.metrics.score import load_scoring_infos, resolve_occ_root
    out, _ = demo_run
    meta = load_scoring_infos(out / "world" / "infos_all.pkl")
    by_stamp = keyframes_by_stamp(meta["infos"])
    stamps = sorted(by_stamp)
    gts = {s: load_occ(resolve_occ_root(meta) / meta["infos"][by_stamp[s]]["occ_path"])[0]
           for s in stamps}
    sets = bag_camera_sets(out / "bag")
    assert set(stamps) <= set(sets.reference_ns.tolist())   # keyframes are sets of the bag
    result, scored, single = score_keyframes(meta, gts, progress=False)
    assert scored == sorted(by_stamp.values())
    assert result["mIoU"] == pytest.approx(100.0) and result["RayIoU"] == pytest.approx(100.0)
    shifted = {stamps[0]: gts[stamps[1]]}
    result, scored, _ = score_keyframes(meta, shifted, progress=False)
    assert scored == [by_stamp[stamps[0]]] and result["mIoU"] < 90.0


def test_the_world_is_reused_only_with_the_same_settings(demo_run):
    out, _ = demo_run
    # The world and bag are reused with the same settings, rebuilt with others.
    spec = WorldSpec((72, 128), seconds=1.5)
    assert build_demo_world(out, spec, progress=False, log=lambda _: None).reused
    assert not world_is_built(out, WorldSpec((72, 128), seed=7, seconds=1.5))
    assert not world_is_built(out, WorldSpec((72, 128), seconds=2.0))


def test_folders_the_demo_did_not_make_are_left_alone(tmp_path):
    (tmp_path / "world").mkdir()
    (tmp_path / "world" / "precious.txt").write_text("mine")
    with pytest.raises(DemoError, match="not made by odg demo"):
        build_demo_world(tmp_path, WorldSpec((72, 128), seconds=0.5), progress=False,
                         log=lambda _: None)
    assert (tmp_path / "world" / "precious.txt").read_text() == "mine"


def test_missing_checkpoint_is_a_clear_error(tmp_path):
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "demo", "--out",
                             str(tmp_path), "--checkpoint", str(tmp_path / "nope.pt")],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert "file not found" in result.stderr and "Traceback" not in result.stderr


def test_shipped_checkpoint_missing_names_it(monkeypatch):
    import odg_ros.resources
    def missing(relative):
        raise FileNotFoundError(relative)
    monkeypatch.setattr(odg_ros.resources, "resource_path", missing)
    with pytest.raises(DemoError, match="model/odg_cpu.pt is missing.*--checkpoint"):
        resolve_checkpoint(None)


def test_camera_sets_and_latency_follow_the_clock():
    ms = 1_000_000
    # CAM_FRONT at 0 and 83 ms; the set's last image 35 ms later; a third set lacks a camera
    sets = CameraSets(np.array([0, 83 * ms, 166 * ms]),
                           np.array([35 * ms, 118 * ms, -1]))
    record = SessionRecord(
        grids=[ReceivedGrid(0, 10.250, np.zeros((1, 1, 1), np.uint8)),
               ReceivedGrid(83 * ms, 10.900, np.zeros((1, 1, 1), np.uint8))],
        clock_wall={35 * ms: 10.000, 118 * ms: 10.500})
    assert grid_latencies_ms(record, sets) == pytest.approx([250.0, 400.0])
    assert sets.num_complete == 2


def test_summary_counts_every_drop_reason_and_scores_only_keyframes():
    infos = [{"cams": {"CAM_FRONT": {"timestamp": 1000}}, "occ_path": "a"},
             {"cams": {"CAM_FRONT": {"timestamp": 2000}}, "occ_path": ""}]
    assert keyframes_by_stamp(infos) == {1_000_000: 0}     # no GT, no keyframe to score
    sets = CameraSets(np.array([1_000_000, 2_000_000]), np.array([1_035_000, 2_035_000]))
    record = SessionRecord(
        grids=[ReceivedGrid(1_000_000, 5.0, np.zeros((1, 1, 1), np.uint8))],
        clock_wall={1_035_000: 4.9},
        diagnostics={"outputs": "1", "stale_sets_dropped": "3", "dropped_incomplete_sets": "1",
                     "corrupt_image": "2", "stage_backbone_ms": "150.0",
                     "stage_decoder_ms": "50.0", "stage_publish_ms": "n/a"})
    report = summarize_session(record, sets, {"infos": infos}, None, [], rate=0.25)
    assert report["dropped"] == 6
    assert report["dropped_by_reason"] == {"stale_sets_dropped": 3,
                                           "dropped_incomplete_sets": 1, "corrupt_image": 2}
    assert report["node_capacity_fps"] == pytest.approx(5.0)
    assert report["latency_ms_p50"] == pytest.approx(100.0)
    assert report["mIoU"] is None and report["keyframes"] == 1
    assert report["fps"] is None                       # one grid: no rate
    text = format_summary(report)
    assert "stale sets dropped 3" in text and "corrupt image 2" in text


def test_bev_shows_the_highest_voxel_with_forward_up_and_left_left():
    from odg_ros.classes import FREE_LABEL, OCC_COLORS
    labels = np.full((4, 3, 5), FREE_LABEL, np.uint8)
    labels[3, 2, 0] = 11        # driveable surface, front-left corner, ground
    labels[3, 2, 4] = 4         # a car above it: the top view shows the car
    labels[0, 0, 1] = 16        # vegetation, back-right corner
    seen = np.zeros(labels.shape, bool)
    seen[3] = True              # only the front row is seen by a camera
    rgb = bev_rgb(labels, seen)
    assert rgb.shape == (4, 3, 3)
    assert tuple(rgb[0, 0]) == OCC_COLORS[4]                 # top-left: +x (front), +y (left)
    assert tuple(rgb[3, 2]) == tuple(int(0.45 * c) for c in OCC_COLORS[16])  # unseen: darker
    assert tuple(rgb[0, 1]) == OCC_COLORS[FREE_LABEL]


def test_the_node_runs_on_the_demo_s_device():
    from odg_ros.ros.demo_session import node_command
    command = node_command("tiny.pt", "bf16", "cuda:1")
    assert command[command.index("device:=cuda:1") - 1] == "-p"
    assert "precision:=bf16" in command


def test_the_prediction_shows_unknown_space_in_its_own_colour():
    """The columns the node's BEV marks -1 (no camera sees them) are UNKNOWN_COLOR; a seen
    road column keeps its class colour."""
    from odg_ros.classes import FREE_LABEL, OCC_COLORS
    labels = np.full((200, 200, 16), FREE_LABEL, np.uint8)
    labels[:, :, 2] = 11                                     # the road
    observed = np.zeros(labels.shape, bool)
    observed[100:, :, 2:] = True                             # seen ahead of the car only
    unknown = unknown_columns(labels, observed)
    assert unknown[:100].all() and not unknown[100:].any()
    rgb = bev_rgb(labels, unknown=unknown)                   # forward up: rows reversed
    assert tuple(rgb[150, 10]) == UNKNOWN_COLOR              # x < 0: behind, not seen
    assert tuple(rgb[50, 10]) == OCC_COLORS[11]              # x > 0: seen road
