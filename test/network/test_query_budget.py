"""Query budgets (network/budget.py): the full budget is the plain decoder; a smaller one
refines the top keep-scores and gives the rest the skip layer's output, in static shapes,
with no host read, one graph per budget and compiled == eager."""
import pytest
import torch

from odg_ros.network import ODG
from odg_ros.network.budget import (QueryBudget, budget_ladder, budget_of, gather_queries,
                                    ranked_queries)
from odg_ros.network.checkpoint import load_model, save_checkpoint
from odg_ros.network.sampling import camera_rows_layout
from odg_ros.bench.census import Census, CensusMode
from testing.helpers import model_inputs, tiny_config


def budget_model(trained=True, seed=0, **overrides):
    cfg = tiny_config(**overrides)
    torch.manual_seed(seed)
    model = ODG(cfg).eval()
    model.decoder.budget_heads.set_trained(trained)
    return model, cfg


def test_ladders_and_fractions():
    cfg = tiny_config()                                       # 20 static, 6 dynamic
    assert budget_ladder(cfg) == [QueryBudget(20, 6), QueryBudget(12, 4), QueryBudget(8, 4)]
    assert QueryBudget(12, 4).refined_fraction(cfg) == pytest.approx(16 / 26)
    assert budget_of(cfg, 0.01) == QueryBudget(4, 4)          # at least one multiple of 4
    big = cfg.replace(num_static=4000, num_dynamic=800)
    assert [(b.static, b.dynamic) for b in budget_ladder(big)] == [(4000, 800), (2400, 400),
                                                                   (1400, 200)]
    for bad in (0.0, 1.5, float("nan"), -0.2):
        with pytest.raises(ValueError, match="0 < fraction <= 1"):
            budget_of(cfg, bad)
    with pytest.raises(ValueError, match="needs more than 2 decoder layers"):
        budget_of(cfg.replace(num_layers=2, points_per_layer=(1, 2)), 0.5)


def test_full_budget_is_the_plain_decoder_with_keep_scores():
    model, cfg = budget_model(trained=False)        # untrained heads may run the full budget
    inputs = model_inputs(cfg, batch=2)
    with torch.no_grad():
        plain = model(*inputs)
        full = model(*inputs, budget=budget_of(cfg, 1.0))
    assert plain.keep_scores is None and full.keep_scores.shape == (2, cfg.num_queries)
    for a, b in zip(plain.layers, full.layers):
        torch.testing.assert_close(a.means, b.means, rtol=0, atol=0)
        torch.testing.assert_close(a.box_logits, b.box_logits, rtol=0, atol=0)


def test_untrained_heads_refuse_a_smaller_budget():
    model, cfg = budget_model(trained=False)
    with pytest.raises(ValueError, match="not trained: it runs the full query budget only"):
        with torch.no_grad():
            model(*model_inputs(cfg), budget=budget_of(cfg, 0.5))


def forced_scores(model, scores):
    """Make the keep-score heads return ``scores`` [B, Q]."""
    model.decoder.budget_heads.scores_of = lambda query, inputs, num_dynamic: scores


def reference_budget(model, cfg, inputs, kept, skipped):
    """The budget decoder written out with plain per-sample indexing (dynamic shapes): layers
    1-2 on every query, 3-6 on ``kept`` (a list of index lists per sample), the skip layer on
    ``skipped``, the last layer put back together in query order."""
    decoder, D = model.decoder, cfg.num_dynamic
    images, ego2img, warp, dt = inputs
    B = images.shape[0]
    feats = model.extract_features(images.flatten(0, 1))
    frames = [[f.unflatten(0, (B, images.shape[1]))[:, t] for f in feats]
              for t in range(images.shape[1])]
    results = []
    for b in range(B):
        geometry = {"ego2img": ego2img[b:b + 1], "ego_warp": warp[b:b + 1],
                    "time_delta": dt[b:b + 1], "image_hw": cfg.image_size, "frame_index": None}
        levels = [camera_rows_layout([frame[level][b:b + 1] for frame in frames],
                                     cfg.num_groups) for level in range(len(frames[0]))]
        query, means, boxes = model.queries(1)
        for layer in decoder.layers[:2]:
            query, means, logits, boxes, box_logits = layer(query, means, boxes, D, geometry,
                                                            levels, True, True)
        keep, skip = torch.tensor(kept[b]), torch.tensor(skipped[b])
        skip_dynamic = skip[skip < D]
        _, skip_means, skip_logits, skip_boxes, skip_box_logits = \
            decoder.budget_heads.skip_layer(query[:, skip], means[:, skip],
                                            boxes[:, skip_dynamic], len(skip_dynamic), geometry,
                                            levels, True, True)
        kept_dynamic = keep[keep < D]
        q, m, bx = query[:, keep], means[:, keep], boxes[:, kept_dynamic]
        for layer in decoder.layers[2:]:
            q, m, logits, bx, box_logits = layer(q, m, bx, len(kept_dynamic), geometry, levels,
                                                 True, True)
        out_means = torch.empty(1, cfg.num_queries, *m.shape[2:])
        out_means[:, keep], out_means[:, skip] = m, skip_means
        out_logits = torch.empty(1, cfg.num_queries, *logits.shape[2:])
        out_logits[:, keep], out_logits[:, skip] = logits, skip_logits
        out_boxes = torch.empty(1, D, 10)
        out_boxes[:, kept_dynamic], out_boxes[:, skip_dynamic] = bx, skip_boxes
        out_box_logits = torch.empty(1, D, box_logits.shape[-1])
        out_box_logits[:, kept_dynamic], out_box_logits[:, skip_dynamic] = (box_logits,
                                                                             skip_box_logits)
        results.append((out_means, out_logits, out_boxes, out_box_logits))
    return [torch.cat(parts) for parts in zip(*results)]


def test_a_budget_refines_the_top_scores_and_skips_the_rest():
    model, cfg = budget_model()
    inputs = model_inputs(cfg, batch=2, seed=3)
    Q, D = cfg.num_queries, cfg.num_dynamic
    g = torch.Generator().manual_seed(1)
    scores = torch.randn(2, Q, generator=g)
    scores[1, 10] = scores[1, 11] = 9.0                # a tie: the lower index wins the last
    budget = QueryBudget(static=5, dynamic=2)
    forced_scores(model, scores)
    with torch.no_grad():
        out = model(*inputs, budget=budget)
    kept, skipped = [], []
    for b in range(2):
        dyn = sorted(range(D), key=lambda i: (-float(scores[b, i]), i))
        sta = sorted(range(D, Q), key=lambda i: (-float(scores[b, i]), i))
        kept.append(sorted(dyn[:2]) + sorted(sta[:5]))
        skipped.append(sorted(dyn[2:]) + sorted(sta[5:]))
    assert out.layers[2].query_index.tolist() == kept
    assert out.layers[2].num_dynamic == 2 and out.layers[2].means.shape[1] == 7
    with torch.no_grad():
        means, logits, boxes, box_logits = reference_budget(model, cfg, inputs, kept, skipped)
    last = out.last
    assert last.means.shape == (2, Q, cfg.points_per_layer[-1], 3) and last.query_index is None
    for got, want in ((last.means, means), (last.logits, logits), (last.boxes, boxes),
                      (last.box_logits, box_logits)):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)
    # the skipped queries really take the skip layer's output (not the last layer's)
    with torch.no_grad():
        full = model(*inputs)
    skip = torch.tensor(skipped[0])
    assert (full.last.means[0, skip] - last.means[0, skip]).abs().max() > 1e-2


def test_ranking_is_a_fixed_size_top_k_per_query_set():
    scores = torch.tensor([[0.1, 0.9, 0.5, 0.3, 0.3, 0.8, -1.0]])
    kept, skipped = ranked_queries(scores, 3, QueryBudget(static=2, dynamic=1))
    assert kept.tolist() == [[1, 3, 5]] and skipped.tolist() == [[0, 2, 4, 6]]
    x = torch.arange(14.0).view(1, 7, 2)
    assert gather_queries(x, kept).tolist() == [[[2, 3], [6, 7], [10, 11]]]


@pytest.mark.parametrize("budget_index", [1, 2])
def test_budget_shapes_do_not_depend_on_the_scene(budget_index):
    model, cfg = budget_model()
    budget = budget_ladder(cfg)[budget_index]
    shapes = []
    for seed in (0, 5):
        with torch.no_grad():
            out = model(*model_inputs(cfg, seed=seed), budget=budget)
        shapes.append([(tuple(l.means.shape), tuple(l.boxes.shape)) for l in out.layers])
    assert shapes[0] == shapes[1]
    assert shapes[0][2][0][1] == budget.static + budget.dynamic


def test_a_budget_step_makes_no_host_read():
    """The census counts every op as a device op: a budget decode has none that waits for
    the device (top-k by sort, gathers: no nonzero, no boolean mask, no .item())."""
    model, cfg = budget_model()
    inputs = model_inputs(cfg)
    feats = [model.extract_features(inputs[0][:, t]) for t in range(cfg.num_frames)]
    for budget in budget_ladder(cfg):
        with torch.no_grad():
            model.decode(feats, *inputs[1:], budget=budget)                # warm index cache
        census = Census()
        with torch.no_grad(), CensusMode(census, device_type=None):
            model.decode(feats, *inputs[1:], budget=budget)
        assert census.per_step(census.ops) > 500
        assert census.per_step(census.syncs) == 0, census.report()
    # the census sees a data-dependent shape: keeping the queries above a score threshold
    census = Census()
    with torch.no_grad(), CensusMode(census, device_type=None):
        out = model.decode(feats, *inputs[1:])
        out.last.means[:, out.last.logits.amax(dim=(0, 2, 3)) > 0]
    assert census.per_step(census.syncs) > 0 and census.waits_by_kind()["shape"] > 0


def test_one_graph_per_budget_and_compiled_equals_eager():
    """fullgraph=True, dynamic=False, a backend that counts the graphs it is given: each
    budget traces once (a data-dependent shape would break the graph), a budget used again
    reuses its graph, and every traced graph gives eager's outputs."""
    model, cfg = budget_model(num_layers=3, points_per_layer=(1, 2, 4))   # quicker to trace
    graphs = []

    def counting_backend(graph_module, example_inputs):
        graphs.append(graph_module)
        return graph_module.forward

    inputs = model_inputs(cfg)
    feats = [model.extract_features(inputs[0][:, t]) for t in range(cfg.num_frames)]

    def decode(feats, ego2img, warp, dt, budget):
        out = model.decode(feats, ego2img, warp, dt, budget=budget)
        return out.last.means, out.last.logits, out.last.boxes, out.keep_scores

    compiled = torch.compile(decode, backend=counting_backend, fullgraph=True, dynamic=False)
    torch._dynamo.reset()
    ladder = budget_ladder(cfg)[1:]
    with torch.no_grad():
        for budget in ladder + ladder[:1]:
            got, want = compiled(feats, *inputs[1:], budget), decode(feats, *inputs[1:], budget)
            for a, b in zip(got, want):
                torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert len(graphs) == len(ladder)


def test_checkpoints_keep_the_heads_and_older_ones_load_untrained(tmp_path):
    model, cfg = budget_model()
    with torch.no_grad():
        model.decoder.budget_heads.static_score.mlp[-1].bias.fill_(0.25)
    save_checkpoint(tmp_path / "with.pt", model)
    loaded, _ = load_model(tmp_path / "with.pt")
    assert loaded.decoder.budget_heads.is_trained
    assert float(loaded.decoder.budget_heads.static_score.mlp[-1].bias[0]) == 0.25
    state = {k: v for k, v in model.state_dict().items() if "budget_heads" not in k}
    torch.save({"config": cfg.to_dict(), "model": state}, tmp_path / "older.pt")
    older, _ = load_model(tmp_path / "older.pt")
    assert not older.decoder.budget_heads.is_trained
    for key, value in state.items():
        torch.testing.assert_close(older.state_dict()[key], value)
