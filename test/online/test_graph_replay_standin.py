"""The node's ``graphs`` mode on the CPU, through a stand-in that replays as a CUDA graph does
(testing.online.RecordedGraph): the ops recorded at the capture run again against the memory
of the capture. So the predictor must copy each set into the static buffers the graph was
captured with and copy each result out, must capture one graph per query budget and replay
the one of the step's budget; a buffer reassigned after the capture is not what the graph
reads, and an op that waits for the device cannot be captured."""
import numpy as np
import pytest
import torch

from odg_ros.network.budget import budget_ladder
from odg_ros.online import predictor as predictor_module
from odg_ros.online.predictor import OnlinePredictor
from testing.online import RecordedGraph, budget_model, eager_reference, make_model, make_sets


@pytest.fixture
def recorded_graphs(monkeypatch):
    """graphs mode on the CPU: the compile left out (eager kernels; compiled ones are checked
    against eager elsewhere), each capture a RecordedGraph."""
    monkeypatch.setattr(predictor_module, "CudaGraphStep", RecordedGraph)
    monkeypatch.setattr(predictor_module, "resolve_mode", lambda mode, device, aoti: mode)
    monkeypatch.setattr(torch, "compile", lambda function, **options: function)
    monkeypatch.setattr(RecordedGraph, "captured", [])
    return RecordedGraph.captured


def test_graphs_mode_outputs_are_each_sets_own_and_stay_as_handed_out(recorded_graphs):
    model, cfg = make_model()
    replayed = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, compile="graphs")
    eager = eager_reference(model, cfg, max_gap=1.0)
    assert replayed.mode == "graphs" and len(recorded_graphs) == 1
    assert not replayed.online_step.parallel_encoder_only      # a graph keeps its threads
    assert len(recorded_graphs[0].ops) > 500                    # the whole step was recorded
    handed_out = []
    for s in make_sets(cfg, 5):
        a, b = replayed.step(*s), eager.step(*s)
        np.testing.assert_array_equal(a.grid, b.grid)           # this set's, not a stale one
        np.testing.assert_array_equal(a.confidence, b.confidence)
        np.testing.assert_array_equal(a.observed, b.observed)
        assert a.boxes == b.boxes
        handed_out.append((a, b))
    assert recorded_graphs[0].replays == 5
    assert len({a.grid.tobytes() for a, _ in handed_out}) > 1   # the sets differ
    for a, b in handed_out:                                     # later replays left them alone
        np.testing.assert_array_equal(a.grid, b.grid)
        np.testing.assert_array_equal(a.confidence, b.confidence)


def test_auto_replays_the_graph_of_each_steps_budget(recorded_graphs):
    """query_budget auto: one capture per rung of the ladder; the steps walk down the ladder
    rung by rung, and each replays its own rung's graph and equals eager auto."""
    model, cfg = budget_model(need_threshold=1e9)             # nothing needed: calm scenes
    replayed = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, compile="graphs",
                               query_budget="auto")
    eager = eager_reference(model, cfg, max_gap=1.0, query_budget="auto")
    ladder = budget_ladder(cfg)
    assert len(recorded_graphs) == len(ladder) == 3
    graph_of = dict(zip(ladder, recorded_graphs))
    for p in (replayed, eager):
        p.policy.patience, p.policy.fresh = 1, False
    used = []
    for s in make_sets(cfg, 4):
        budget = replayed.budget
        before = graph_of[budget].replays
        a, b = replayed.step(*s), eager.step(*s)
        assert graph_of[budget].replays == before + 1           # its own graph, once
        np.testing.assert_array_equal(a.grid, b.grid)
        assert a.boxes == b.boxes and a.query_budget == b.query_budget
        used.append(a.query_budget)
    assert used == [b.name for b in ladder] + [ladder[-1].name]
    assert [g.replays for g in recorded_graphs] == [1, 1, 2]


@pytest.mark.parametrize("buffer", ["_packed", "_images"])
def test_a_static_buffer_reassigned_after_the_capture_gives_stale_results(recorded_graphs,
                                                                          buffer):
    """What a GPU does to a predictor that puts a set into a new tensor instead of copying it
    into the captured one: the graph keeps reading the capture's buffer (the warm-up's blank
    inputs), so its results are not the set's. The stand-in shows it as the GPU would."""
    model, cfg = make_model()
    replayed = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, compile="graphs")
    eager = eager_reference(model, cfg, max_gap=1.0)
    new = getattr(replayed, buffer).clone()
    # on the CPU the host and the device buffer are one tensor: both become the new one
    setattr(replayed, buffer, new)
    setattr(replayed, buffer + "_host", new)
    differ = [(replayed.step(*s).grid != eager.step(*s).grid).any() for s in make_sets(cfg, 3)]
    assert all(differ)


def test_a_replay_writes_the_ring_memory_of_its_capture(recorded_graphs):
    """The feature ring reassigned after the capture (``ring.use_memory(...)``): the graph
    still writes each set's features into the memory it was captured with."""
    model, cfg = make_model()
    replayed = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, compile="graphs")
    captured = replayed.ring.memory
    before = [m.clone() for m in captured]
    replayed.ring.use_memory([m.clone() for m in captured])
    replayed.step(*make_sets(cfg, 1)[0])
    assert all(torch.equal(m, b) for m, b in zip(replayed.ring.memory, before))
    assert any(not torch.equal(m, b) for m, b in zip(captured, before))


def test_an_op_that_waits_for_the_device_cannot_be_captured():
    def step(images, packed):
        return (images * float(packed.sum()),)                  # .item(): a host read
    with pytest.raises(RuntimeError, match="not permitted when stream is capturing"):
        RecordedGraph(step, torch.ones(3), torch.ones(2), "cpu")
