"""The online step under a query budget: each budget is one static-shape step with no host
read, compiled == eager, one graph per budget; ``query_budget auto`` follows the scene."""
import numpy as np
import pytest
import torch

from odg_ros.geometry import ego_warp
from odg_ros.network import ODG
from odg_ros.network.budget import budget_ladder, budget_of
from odg_ros.network.feature_ring import FeatureRing
from odg_ros.online.predictor import OnlinePredictor
from odg_ros.preprocess import normalize
from testing.helpers import published_grid, tiny_config
from testing.online import HostSyncCounter, budget_model, make_sets


def ring_outputs(model, cfg, sets, budget):
    """The dynamic ring path (``ODG.decode_ring`` over the filled slots) under ``budget``."""
    ring, held, outputs = FeatureRing(cfg.num_frames, cfg.num_groups), [], []
    with torch.inference_mode():
        for images, ego2img, pose, stamp in sets:
            ring.push(model.extract_features(normalize(torch.from_numpy(images))[None]))
            held = [(ego2img, pose, stamp)] + held[:cfg.num_frames - 1]
            e2i = torch.tensor(np.stack([h[0] for h in held]), dtype=torch.float32)[None]
            warps = torch.tensor(np.stack([ego_warp(held[0][1], h[1]) for h in held]),
                                 dtype=torch.float32)[None]
            deltas = torch.tensor([held[0][2] - h[2] for h in held], dtype=torch.float32)[None]
            outputs.append(model.decode_ring(ring, e2i, warps, deltas, budget=budget))
    return outputs


def test_a_fixed_budget_step_equals_the_budget_decoder_over_the_ring():
    model, cfg = budget_model()
    budget = budget_of(cfg, 0.5)
    sets = make_sets(cfg, 4)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, query_budget=0.5)
    full = OnlinePredictor(model, cfg, "cpu", max_gap=1.0)
    expected = ring_outputs(model, cfg, sets, budget)
    for s, output in zip(sets, expected):
        got, plain = predictor.step(*s), full.step(*s)
        assert got.query_budget == budget.name and got.refined_fraction == pytest.approx(
            (budget.static + budget.dynamic) / cfg.num_queries)
        assert plain.query_budget == "full" and plain.refined_fraction == 1.0
        np.testing.assert_array_equal(got.grid, published_grid(output, cfg)[0][0].numpy())
        assert (got.grid != plain.grid).any()      # the budget changes the output


def test_auto_steps_down_on_calm_scenes_and_back_up_when_needed():
    """Needs forced through the keep-score threshold: a busy first frame keeps the full
    budget; then none needed -> one rung down after every three calm steps; all needed ->
    the full budget at once; a reset -> full, and the new drive's first needs at once."""
    model, cfg = budget_model(need_threshold=-1e9)  # the first frame: every query needed
    heads = model.decoder.budget_heads
    names = [b.name for b in budget_ladder(cfg)]
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, query_budget="auto")
    sets = make_sets(cfg, 10)
    used = [predictor.step(*sets[0]).query_budget]
    heads.threshold = 1e9                           # then none
    used += [predictor.step(*s).query_budget for s in sets[1:8]]
    assert used == [names[0]] * 4 + [names[1]] * 3 + [names[2]]
    heads.threshold = -1e9                          # every query needed from now on
    used = [predictor.step(*s).query_budget for s in sets[8:]]
    assert used == [names[2], names[0]]
    heads.threshold = 1e9
    result = predictor.step(*sets[0])               # back in time: a new drive
    assert result.history_reset == "time_backwards" and result.query_budget == names[0]
    assert predictor.step(*sets[1]).query_budget == names[2]


def test_a_busy_scene_keeps_the_full_budget():
    """Objects published keep the dynamic queries refined, whatever the keep-scores say: with
    every box above its threshold (a scene full of objects) auto never steps down, where the
    same steps without objects step down the ladder."""
    cfg = tiny_config(score_threshold=0.0, box_score_threshold=0.0)
    torch.manual_seed(0)
    model = ODG(cfg).eval()
    model.decoder.budget_heads.set_trained(True, 1e9)    # the keep-scores need nothing
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, query_budget="auto")
    steps = [predictor.step(*s) for s in make_sets(cfg, 7)]
    assert all(len(step.boxes) == cfg.num_dynamic for step in steps)
    assert {step.query_budget for step in steps} == {budget_ladder(cfg)[0].name}
    assert {step.refined_fraction for step in steps} == {1.0}


def test_a_budget_step_reads_nothing_back():
    model, cfg = budget_model()
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, query_budget="auto")
    for s in make_sets(cfg, 2):
        predictor.step(*s)
    for budget in budget_ladder(cfg)[1:]:
        with torch.inference_mode(), HostSyncCounter() as counter:
            predictor.online_step(predictor._images, predictor._packed, budget)
        assert counter.ops > 1000 and counter.syncs == [], counter.syncs


def test_auto_compiles_one_graph_per_budget_and_equals_eager():
    """fullgraph, dynamic=False, a counting backend: the warm-up traces each rung once, the
    steps (which walk down the ladder) trace nothing more, and equal eager auto's. (Three
    decoder layers: tracing time grows with them.)"""
    model, cfg = budget_model(need_threshold=1e9, num_layers=3, points_per_layer=(1, 2, 4))
    graphs = []

    def counting_backend(graph_module, example_inputs):
        graphs.append(graph_module)
        return graph_module.forward

    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, query_budget="auto")
    predictor._function = torch.compile(predictor.online_step, backend=counting_backend,
                                        fullgraph=True, dynamic=False)
    torch._dynamo.reset()
    predictor._warm_up()
    assert len(graphs) == len(budget_ladder(cfg))
    eager = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, query_budget="auto")
    predictor.policy.patience = eager.policy.patience = 1
    predictor.policy.fresh = eager.policy.fresh = False    # rung by rung, not straight down
    used = []
    for s in make_sets(cfg, 4):
        a, b = predictor.step(*s), eager.step(*s)
        np.testing.assert_array_equal(a.grid, b.grid)
        assert a.boxes == b.boxes and a.query_budget == b.query_budget
        used.append(a.query_budget)
    assert used == [b.name for b in budget_ladder(cfg)] + [used[-1]] and len(graphs) == 3


def test_budget_settings_are_checked():
    model, cfg = budget_model()
    for bad in ("some", "0", "1.5", "nan"):
        with pytest.raises(ValueError, match="query_budget|fraction"):
            OnlinePredictor(model, cfg, "cpu", query_budget=bad)
    assert OnlinePredictor(model, cfg, "cpu", query_budget="1.0").budgets == [None]
    model.decoder.budget_heads.set_trained(False)
    with pytest.raises(ValueError, match="not trained; use query_budget full"):
        OnlinePredictor(model, cfg, "cpu", query_budget="auto")
