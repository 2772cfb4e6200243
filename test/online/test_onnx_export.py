"""``odg export --onnx`` and its host side (online/onnx_inputs.py): a deployment that feeds
the graph from CameraInfo, extrinsics, poses and stamps gets the node's grids, set after
set, with the history carried through the graph's inputs and outputs; the inputs come out
of the node's own geometry and history code, without torch."""
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from odg_ros.commands import main
from odg_ros.geometry import make_transform
from odg_ros.network.checkpoint import load_model
from odg_ros.online.errors import BadInput
from odg_ros.online.onnx_inputs import StepInputs, camera_set_geometry, network_input
from odg_ros.online.pipeline import OnlinePipeline, PipelineSettings
from odg_ros.online.predictor import OnlinePredictor
from testing.helpers import tiny_config, write_tiny_checkpoint
from testing.online import CAMS, HW, OFFSETS, RIG, feed_set, scaled_K, set_images

# A drive with history: sets 0.25 s apart and the node's history_interval 0.45 s, so every
# other set replaces the newest frame; the 3-frame history fills, then drops its oldest
# (set 5), and a 1.5 s gap restarts it (set 6).
STARTS = (10.0, 10.25, 10.5, 10.75, 11.0, 11.25, 12.75, 13.0)
REPLACES = (False, False, True, False, True, False, False, False)
LENGTHS = (1, 2, 2, 3, 3, 3, 1, 2)
FREE = 17


def pose_at(t):
    """T_global_from_ego: 8 m/s, turning at 0.2 rad/s."""
    yaw = 0.2 * t
    return make_transform([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)], (8.0 * t, 0.3 * t, 0.0))


def node_pipeline(model, cfg):
    """The node's pipeline (CameraInfo checks, poses at every camera stamp, decoding,
    resizing) around its predictor, at the node's history settings."""
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, min_interval=0.45)
    pipeline = OnlinePipeline(predictor, PipelineSettings.from_parameters(CAMS),
                              lambda camera, frame_id, t: RIG.cameras[camera].sensor2ego,
                              pose_lookup=pose_at)
    for name in CAMS:
        pipeline.on_camera_info(name, scaled_K(name), *HW, frame_id=name)
    return pipeline


def deployment_inputs(feeder, images, start):
    """What a deployment does with one set: CameraInfo K and size, extrinsics, the pose at
    each camera's stamp -> the graph's named inputs."""
    ego2img, bounds = camera_set_geometry(
        [scaled_K(c) for c in CAMS], [HW] * len(CAMS), [RIG.cameras[c].sensor2ego for c in CAMS],
        [pose_at(start + offset) for offset in OFFSETS], pose_at(start), feeder.input_hw)
    return feeder.feeds(network_input(images, feeder.input_hw), ego2img, pose_at(start),
                        start, bounds)


def agreement(labels, grid):
    """(share of all voxels with the node's label, share of the voxels occupied in
    either): the grids are sparse, so only the second sees a wrong history."""
    occupied = (labels != FREE) | (grid != FREE)
    return (labels == grid).mean(), (labels[occupied] == grid[occupied]).mean()


def test_exported_step_fed_by_the_builder_gives_the_node_grids(tmp_path, capfd):
    ort = pytest.importorskip("onnxruntime", reason="onnxruntime is not installed")
    pytest.importorskip("onnxscript", reason="onnxscript (torch.onnx's exporter) is not "
                        "installed")
    # two decoder layers keep the export short; 120 queries of 16 points and thresholds 0
    # give ~700 occupied voxels and 20 boxes to compare
    checkpoint = write_tiny_checkpoint(tmp_path / "tiny.pt", num_layers=2,
                                       points_per_layer=(2, 16), num_static=100,
                                       num_dynamic=20, num_frames=3, score_threshold=0.0,
                                       box_score_threshold=0.0)
    path = tmp_path / "step.onnx"
    capfd.readouterr()
    assert main(["export", "--checkpoint", str(checkpoint), "--onnx", str(path)]) == 0
    out, err = capfd.readouterr()
    assert err == ""                                     # no warnings, no exporter chatter
    report = json.loads(out)
    assert sorted(p.name for p in tmp_path.glob("step.onnx*")) == ["step.onnx"]  # no .data
    assert report["files"] == {str(path): path.stat().st_size}
    assert report["inputs"]["ego2img"] == "float32 [3, 6, 4, 4]"
    assert report["outputs"]["labels"] == "uint8 [200, 200, 16]"
    model, cfg = load_model(checkpoint)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert json.loads(session.get_modelmeta().custom_metadata_map["odg.free_label"]) == FREE
    names = [o.name for o in session.get_outputs()]
    pipeline = node_pipeline(model, cfg)
    node_ring = pipeline.predictor.ring
    feeder = StepInputs.for_session(session)
    for i, start in enumerate(STARTS):
        images = set_images(i)
        assert feed_set(pipeline, start, images, now=start + 0.1)
        node = pipeline.process(pipeline.next_set(timeout=0.1))
        feeds = deployment_inputs(feeder, images, start)
        assert (bool(feeds["replace_newest"][0]), int(feeds["history_length"][0])) == \
            (REPLACES[i], LENGTHS[i]) == (REPLACES[i], node.num_frames)
        got = dict(zip(names, session.run(None, feeds)))
        everywhere, occupied = agreement(got["labels"], node.grid)
        assert everywhere >= 0.999 and occupied >= 0.999, (i, everywhere, occupied)
        assert (node.grid != FREE).sum() > 500
        assert (got["observed"].astype(bool) == node.observed).mean() >= 0.999
        valid = got["valid"]
        assert valid.sum() == len(node.boxes) > 0
        assert got["label"][valid].tolist() == [b["label"] for b in node.boxes]
        np.testing.assert_allclose(got["score"][valid], [b["score"] for b in node.boxes],
                                   atol=1e-4)
        np.testing.assert_allclose(got["boxes"][valid, :3],
                                   [b["center"] for b in node.boxes], atol=1e-3)
        # the history the graph returns is the node's ring, frame t in slot t
        for level, memory in enumerate(node_ring.memory):
            ring = memory.view(node_ring.capacity, -1, *memory.shape[1:]).numpy()
            for t, slot in enumerate(node_ring.slots()):
                np.testing.assert_allclose(got[f"features_{level}_out"][t], ring[slot],
                                           atol=1e-4, rtol=1e-4)
        if i == 5:          # a full history that just dropped its oldest frame
            for what, broken in _broken(feeds):
                wrong = dict(zip(names, session.run(None, broken)))["labels"]
                assert agreement(wrong, node.grid)[1] < 0.99, what
            unused = {**feeds, "history_length": np.array([2], np.int64)}
            for name in ("ego2img", "ego_warp", "time_delta"):   # frames beyond the length
                unused[name] = feeds[name].copy()
                unused[name][2:] = 0
            ignored = dict(zip(names, session.run(None, unused)))["labels"]
            shorter = dict(zip(names, session.run(
                None, {**feeds, "history_length": np.array([2], np.int64)})))["labels"]
            assert np.array_equal(ignored, shorter)
        feeder.keep([got[f"features_{level}_out"] for level in range(len(feeder.features))])
    assert feeder.last_reset is None and feeder.history.resets["gap"] == 1


def _broken(feeds):
    """Feeds a deployment could get wrong: no history, no ego motion, the history shifted
    where it should not, the history length ignored -> (what, feeds)."""
    yield "features fed zeros", {**feeds, **{k: np.zeros_like(v) for k, v in feeds.items()
                                             if k.startswith("features_")}}
    yield "identity ego warps", {**feeds, "ego_warp": np.broadcast_to(
        np.eye(4, dtype=np.float32), feeds["ego_warp"].shape).copy()}
    yield "replace_newest flipped", {**feeds, "replace_newest": ~feeds["replace_newest"]}
    yield "history_length 1", {**feeds, "history_length": np.array([1], np.int64)}


def test_builder_inputs_are_the_node_geometry():
    """Set after set (replacements, a wrapped ring, a reset), the builder's named inputs
    equal the geometry the node packs for its step, slot by slot: same float32 values."""
    cfg = tiny_config(num_frames=3)
    torch.manual_seed(0)
    from odg_ros.network import ODG
    pipeline = node_pipeline(ODG(cfg).eval(), cfg)
    predictor = pipeline.predictor
    k = predictor.layout.capacity
    shapes = [(k, m.shape[0] // k, *m.shape[1:]) for m in predictor.ring.memory]
    feeder = StepInputs(cfg.num_cams, cfg.image_size, shapes)
    for i, start in enumerate(STARTS):
        images = set_images(i)
        assert feed_set(pipeline, start, images, now=start + 0.1)
        pipeline.process(pipeline.next_set(timeout=0.1))
        feeds = deployment_inputs(feeder, images, start)
        ego2img, warps, deltas, frame_index, slot = predictor.layout.unpack(predictor._packed)
        slots = predictor.ring.slots()
        n = len(slots)
        assert int(feeds["history_length"][0]) == n and int(slot[0]) == slots[0]
        assert frame_index.tolist() == [slots[min(t, n - 1)] for t in range(cfg.num_frames)]
        np.testing.assert_array_equal(feeds["ego2img"][:n], ego2img[0, slots].numpy())
        np.testing.assert_array_equal(feeds["ego_warp"][:n], warps[0, slots].numpy())
        np.testing.assert_array_equal(feeds["time_delta"][:n], deltas[0, slots].numpy())
        _, img2ego, bounds = predictor.layout.current_view(predictor._packed)
        np.testing.assert_array_equal(feeds["img2ego"], img2ego.numpy())
        np.testing.assert_array_equal(feeds["image_bounds"], bounds.numpy())
        assert feeds["images"].shape == (cfg.num_cams, *cfg.image_size, 3)
        assert feeds["replace_newest"][0] == REPLACES[i]
        assert feeds["time_delta"][0] == 0 and np.all(np.diff(feeds["time_delta"][:n]) > 0)


def test_builder_defaults_are_the_node_defaults():
    from odg_ros.online import onnx_inputs
    from odg_ros.online.parameters import load_schema
    schema = load_schema()
    assert (onnx_inputs.MAX_GAP, onnx_inputs.MAX_SPEED, onnx_inputs.MIN_INTERVAL) == (
        schema["history_max_gap"].default, schema["max_speed"].default,
        schema["history_interval"].default)


def test_builder_runs_without_torch():
    """A deployment with onnxruntime and this package, without torch."""
    script = textwrap.dedent("""
        import sys
        class NoTorch:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] == "torch":
                    raise ImportError("no torch here")
        sys.meta_path.insert(0, NoTorch())
        import numpy as np
        from odg_ros.geometry import make_transform
        from odg_ros.online.onnx_inputs import StepInputs, camera_set_geometry, network_input
        K = [[[500.0, 0, 800], [0, 500, 450], [0, 0, 1]]] * 2
        sensor2ego = [make_transform([0.5, -0.5, 0.5, -0.5], (1.5, 0, 1.6))] * 2
        feeder = StepInputs(2, (32, 88), [(3, 4, 10, 11, 8)])
        for t in (0.0, 0.5, 1.0):
            pose = make_transform([1, 0, 0, 0], (5 * t, 0, 0))
            ego2img, bounds = camera_set_geometry(K, [(900, 1600)] * 2, sensor2ego,
                                                  [pose] * 2, pose, feeder.input_hw)
            images = network_input([np.zeros((900, 1600, 3), np.uint8)] * 2, (32, 88))
            feeds = feeder.feeds(images, ego2img, pose, t, bounds)
        assert "torch" not in sys.modules
        print(sorted(feeds), feeds["ego_warp"][1, 0, 3], feeds["image_bounds"][0].tolist())
    """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    assert "['ego2img', 'ego_warp', 'features_0', 'history_length', 'image_bounds', " \
        "'images', 'img2ego', 'replace_newest', 'time_delta']" in run.stdout
    # frame 1 is 0.5 s = 2.5 m back: the current ego's origin lies at x = 2.5 m in it
    assert " 2.5 " in run.stdout
    # 900 x 1600 -> 50 x 88, its top 18 rows cropped off: they lie above row 0
    assert "[0.0, -18.0, 88.0, 32.0]" in run.stdout


def test_builder_refuses_bad_inputs_in_one_line():
    feeder = StepInputs(6, (64, 176), [(3, 4, 10, 11, 8)])
    K = [scaled_K(c) for c in CAMS]
    sensor2ego = [RIG.cameras[c].sensor2ego for c in CAMS]
    poses = [pose_at(10.0)] * 6
    bad_K = [np.diag([0.0, 0.0, 1.0])] + K[1:]
    with pytest.raises(BadInput, match="bad_camera_info: .*camera 0"):
        camera_set_geometry(bad_K, [HW] * 6, sensor2ego, poses, poses[0], (64, 176))
    with pytest.raises(ValueError, match="not rigid"):
        camera_set_geometry(K, [HW] * 6, [2 * np.eye(4)] * 6, poses, poses[0], (64, 176))
    ego2img, bounds = camera_set_geometry(K, [HW] * 6, sensor2ego, poses, poses[0], (64, 176))
    with pytest.raises(ValueError, match=r"images uint8 \[6, 32, 88, 3\]: expected uint8 "
                                         r"\[6, 64, 176, 3\]"):
        feeder.feeds(np.zeros((6, 32, 88, 3), np.uint8), ego2img, poses[0], 10.0, bounds)
    with pytest.raises(ValueError, match="rigid transform at a finite stamp"):
        feeder.feeds(np.zeros((6, 64, 176, 3), np.uint8), ego2img, 2 * np.eye(4), 10.0)
    assert len(feeder.history) == 0                     # nothing half-done


def test_named_step_refuses_a_geometry_layout_it_does_not_pack(monkeypatch):
    from odg_ros.online.onnx_export import NamedInputStep
    from odg_ros.online.step import GeometryLayout, OnlineStep
    original = GeometryLayout.__init__

    def with_one_more_field(self, capacity, num_cams, num_frames):
        original(self, capacity, num_cams, num_frames)
        self.slices["speed"] = slice(self.size, self.size + 1)
        self.size += 1
    monkeypatch.setattr(GeometryLayout, "__init__", with_one_more_field)
    cfg = tiny_config(num_frames=2)
    from odg_ros.network import ODG
    with pytest.raises(RuntimeError, match="update NamedInputStep"):
        NamedInputStep(OnlineStep(ODG(cfg).eval(), cfg, 2, "cpu"))


def test_export_needs_one_output(tmp_path, capsys):
    checkpoint = write_tiny_checkpoint(tmp_path / "tiny.pt")
    for argv in ([], ["--out", str(tmp_path / "a.pt"), "--onnx", str(tmp_path / "a.onnx")]):
        assert main(["export", "--checkpoint", str(checkpoint), *argv]) == 2
        assert "--out" in capsys.readouterr().err


def test_a_graph_too_large_for_one_file_names_every_file(tmp_path, monkeypatch):
    """Below the limit the weights go back into the graph (one file that loads alone);
    above it they stay beside it, and both files are named with their sizes; either way
    the metadata is in the graph."""
    ort = pytest.importorskip("onnxruntime", reason="onnxruntime is not installed")
    pytest.importorskip("onnxscript", reason="onnxscript is not installed")
    from odg_ros.online import onnx_export
    model = torch.nn.Linear(64, 64).eval()
    x = torch.randn(1, 64)
    for limit, expected in ((2 ** 31, ["one.onnx"]), (1, ["one.onnx", "one.onnx.data"])):
        monkeypatch.setattr(onnx_export, "SINGLE_FILE_LIMIT", limit)
        path = tmp_path / str(limit) / "one.onnx"
        path.parent.mkdir()
        with onnx_export._quiet_export():
            torch.onnx.export(model, (x,), str(path), dynamo=True, external_data=True,
                              verbose=False)
        files = onnx_export._single_file_if_it_fits(path, {"odg.model": "linear"})
        assert [p.name for p, _ in files] == expected
        assert sorted(p.name for p in path.parent.iterdir()) == expected
        assert all(size == p.stat().st_size > 0 for p, size in files)
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        assert session.get_modelmeta().custom_metadata_map == {"odg.model": "linear"}
        np.testing.assert_allclose(session.run(None, {session.get_inputs()[0].name:
                                                      x.numpy()})[0],
                                   model(x).detach().numpy(), atol=1e-5)
