"""``odg export --onnx``: the online step over a full ring, run in onnxruntime on the CPU,
equals the PyTorch step (grid, boxes, visibility and the updated ring) within the tolerance
stated here; the export is one self-contained file, or names every file it wrote."""
import json

import numpy as np
import pytest
import torch

from odg_ros.online.predictor import OnlinePredictor
from odg_ros.commands import main
from odg_ros.network.checkpoint import load_model
from testing.helpers import write_tiny_checkpoint
from testing.online import make_sets

ort = pytest.importorskip("onnxruntime", reason="onnxruntime is not installed")
pytest.importorskip("onnxscript", reason="onnxscript (torch.onnx's exporter) is not installed")


def test_onnx_step_equals_pytorch_over_a_full_ring(tmp_path, capsys):
    from odg_ros.online.onnx_export import OUTPUT_NAMES, StatelessStep
    from odg_ros.online.step import OnlineStep
    # two decoder layers and two frames keep the export short; thresholds 0 keep every
    # point and box, so the grids compared are not all free
    checkpoint = write_tiny_checkpoint(tmp_path / "tiny.pt", num_layers=2,
                                       points_per_layer=(2, 4), num_frames=2,
                                       score_threshold=0.0, box_score_threshold=0.0)
    path = tmp_path / "step.onnx"
    assert main(["export", "--checkpoint", str(checkpoint), "--onnx", str(path)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert sorted(p.name for p in tmp_path.glob("step.onnx*")) == ["step.onnx"]  # no .data
    assert report["files"] == {str(path): path.stat().st_size}
    assert report["bytes"] == path.stat().st_size
    model, cfg = load_model(checkpoint)
    stateless = StatelessStep(OnlineStep(model, cfg, cfg.num_frames, "cpu").eval()).eval()
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    # real geometry and a real ring: a node that has seen k + 1 sets (wrapped once)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0)
    sets = make_sets(cfg, cfg.num_frames + 2)
    for s in sets[:-1]:
        predictor.step(*s)
    ring = [m.clone() for m in predictor.ring._memory]
    images, ego2img, pose, stamp = sets[-1]
    predictor.step(images, ego2img, pose, stamp)          # fills predictor._packed
    packed = predictor._packed.clone()
    feeds = {"images": images, "packed": packed.numpy()}
    feeds.update({f"ring_{i}": m.numpy() for i, m in enumerate(ring)})
    got = dict(zip([o.name for o in session.get_outputs()], session.run(None, feeds)))
    with torch.no_grad():
        expected = stateless(torch.from_numpy(images), packed, *ring)
    names = list(OUTPUT_NAMES) + [f"ring_{i}_out" for i in range(len(ring))]
    expected = dict(zip(names, (t.numpy() for t in expected)))
    labels, free = expected["labels"], cfg.num_classes
    assert (labels != free).sum() > 50 and expected["valid"].sum() > 0   # a real comparison
    # The tolerance, as it is: a label may differ where a float sum puts a point on a voxel
    # border (under 0.1 % of the voxels); the confidence
    # is within 1 (of 255) except at those voxels and next to them, where the padding
    # (3 x 3 x 3 maximum) takes another label's score: there it may differ by anything.
    differ = (got["labels"] != labels).reshape(cfg.grid_shape)
    assert differ.mean() < 1e-3
    near = torch.nn.functional.max_pool3d(torch.from_numpy(differ).float()[None, None], 3,
                                          stride=1, padding=1)[0, 0].numpy() > 0
    confidence = np.abs(got["confidence"].astype(int) - expected["confidence"])
    assert confidence.reshape(cfg.grid_shape)[~near].max() <= 1
    # visibility follows the labels: equal but for float rounding on rays
    assert (got["observed"] != expected["observed"]).mean() < 1e-3
    assert expected["observed"].sum() > 1000
    np.testing.assert_array_equal(got["valid"], expected["valid"])
    np.testing.assert_array_equal(got["label"], expected["label"])
    np.testing.assert_allclose(got["score"], expected["score"], atol=1e-4)
    np.testing.assert_allclose(got["boxes"], expected["boxes"], atol=1e-3, rtol=1e-3)
    for i, m in enumerate(predictor.ring._memory):          # the ring the node holds now
        np.testing.assert_allclose(got[f"ring_{i}_out"], m.numpy(), atol=1e-4, rtol=1e-4)


def test_export_needs_one_output(tmp_path, capsys):
    checkpoint = write_tiny_checkpoint(tmp_path / "tiny.pt")
    for argv in ([], ["--out", str(tmp_path / "a.pt"), "--onnx", str(tmp_path / "a.onnx")]):
        assert main(["export", "--checkpoint", str(checkpoint), *argv]) == 2
        assert "--out" in capsys.readouterr().err


def test_a_graph_too_large_for_one_file_names_every_file(tmp_path, monkeypatch):
    """Below the limit the weights go back into the graph (one file that loads alone);
    above it they stay beside it, and both files are named with their sizes."""
    from odg_ros.online import onnx_export
    model = torch.nn.Linear(64, 64).eval()
    x = torch.randn(1, 64)
    for limit, expected in ((2 ** 31, ["one.onnx"]), (1, ["one.onnx", "one.onnx.data"])):
        monkeypatch.setattr(onnx_export, "SINGLE_FILE_LIMIT", limit)
        path = tmp_path / str(limit) / "one.onnx"
        path.parent.mkdir()
        torch.onnx.export(model, (x,), str(path), dynamo=True, external_data=True,
                          verbose=False)
        files = onnx_export._single_file_if_it_fits(path)
        assert [p.name for p, _ in files] == expected
        assert sorted(p.name for p in path.parent.iterdir()) == expected
        assert all(size == p.stat().st_size > 0 for p, size in files)
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        np.testing.assert_allclose(session.run(None, {session.get_inputs()[0].name:
                                                      x.numpy()})[0],
                                   model(x).detach().numpy(), atol=1e-5)