"""The node's ``graphs`` mode on the CPU, through a stand-in with what a CUDA graph does to a
step: it reads the static input buffers it was captured with, and every replay rewrites the
output tensors of the capture. The predictor must copy each set into those buffers and copy
each result out, or results come out stale: a set's outputs would be an earlier set's, and a
prediction handed out would change at the next replay."""
import numpy as np
import torch

from odg_ros.online import predictor as predictor_module
from odg_ros.online.predictor import OnlinePredictor
from test_online_predictor import make_model, make_sets


class StaticOutputsReplay:
    """A CUDA graph's behaviour, on the CPU (predictor.CudaGraphStep's interface)."""

    captures = 0

    def __init__(self, function, images, packed, device):
        StaticOutputsReplay.captures += 1
        self.function, self.images, self.packed = function, images, packed
        self.outputs = [o.clone() for o in function(images, packed)]

    def replay(self):
        for buffer, value in zip(self.outputs, self.function(self.images, self.packed)):
            buffer.copy_(value)
        return self.outputs


def test_graphs_mode_outputs_are_each_sets_own_and_stay_as_handed_out(monkeypatch):
    monkeypatch.setattr(predictor_module, "CudaGraphStep", StaticOutputsReplay)
    monkeypatch.setattr(predictor_module, "resolve_mode", lambda mode, device, aoti: mode)
    monkeypatch.setattr(torch, "compile", lambda function, **options: function)
    model, cfg = make_model()
    replayed = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, compile="graphs")
    eager = OnlinePredictor(model, cfg, "cpu", max_gap=1.0)
    assert replayed.mode == "graphs" and StaticOutputsReplay.captures == 1
    handed_out = []
    for s in make_sets(cfg, 5):
        a, b = replayed.step(*s), eager.step(*s)
        np.testing.assert_array_equal(a.grid, b.grid)           # this set's, not a stale one
        np.testing.assert_array_equal(a.confidence, b.confidence)
        assert a.boxes == b.boxes
        handed_out.append((a, b))
    assert len({a.grid.tobytes() for a, _ in handed_out}) > 1   # the sets differ
    for a, b in handed_out:                                     # later replays left them alone
        np.testing.assert_array_equal(a.grid, b.grid)
        np.testing.assert_array_equal(a.confidence, b.confidence)
