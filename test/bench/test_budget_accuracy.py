"""The bounds of the budget accuracy study (odg_ros/bench/budget_accuracy.py): a perfect
keep-score ranks the queries by the keep-scores' own target on the keyframe itself, a
ground-truth oracle by the correct voxels refining wins."""
import pytest
import torch

from odg_ros.network.budget import budget_of
from odg_ros.train import budget_heads as heads
from odg_ros.network.postprocess import occupancy_grid
from testing.helpers import model_inputs, tiny_config
from odg_ros.network import decoder as decoder_module
from odg_ros.bench.budget_accuracy import Config, configurations, oracle_scores
from tools.eval_budget import main


@pytest.fixture(scope="module")
def model_and_cfg():
    cfg = tiny_config(image_size=(32, 88), num_frames=2, score_threshold=0.0)
    torch.manual_seed(0)
    from odg_ros.network import ODG
    model = ODG(cfg).eval()
    heads.init_skip_layer(model)
    model.decoder.budget_heads.set_trained(True)
    return model, cfg


def keyframe(model, cfg, seed):
    """(frames' features, batch) as budget_accuracy.evaluate_class hands them over."""
    images, ego2img, ego_warp, time_delta = model_inputs(cfg, seed=seed)
    B, T = images.shape[:2]
    with torch.no_grad():
        feats = model.extract_features(images.flatten(0, 1))
        grid = occupancy_grid(model(images, ego2img, ego_warp, time_delta), cfg)[0][0]
    frames = [[f.unflatten(0, (B, T))[:, t] for f in feats] for t in range(T)]
    batch = {"ego2img": ego2img, "ego_warp": ego_warp, "time_delta": time_delta,
             "occ_mask_camera": torch.ones((1, *grid.shape), dtype=torch.bool),
             "occ_semantics": grid[None].long()}
    return frames, batch, (images, ego2img, ego_warp, time_delta)


def test_a_perfect_keep_score_is_the_target_the_keep_scores_learn(model_and_cfg):
    model, cfg = model_and_cfg
    frames, batch, inputs = keyframe(model, cfg, seed=3)
    got = oracle_scores(model, frames, batch)["change"][0]
    record = heads.keyframe_record(model, inputs, batch["occ_mask_camera"][0])
    skipped = heads.skip_layer_output(model, record)[:2]
    teacher = (record["teacher"]["means"], record["teacher"]["logits"].float())
    weights = heads.keyframe_class_weights(*teacher, record["mask"], cfg)
    expected = heads.output_change(teacher, skipped, record["mask"], weights, cfg)
    assert got.shape == (cfg.num_queries,) and float(expected.sum()) > 0
    # the cached record holds the teacher's logits in float16: a few points flip a voxel
    assert float(torch.isclose(got, expected, rtol=1e-4).float().mean()) > 0.75
    assert torch.allclose(got, expected, rtol=0.05)


def test_an_oracle_budget_refines_the_queries_its_oracle_ranks_first(model_and_cfg):
    model, cfg = model_and_cfg
    frames, batch, _ = keyframe(model, cfg, seed=4)
    budget = budget_of(cfg, 0.35)
    # ground truth = the full model's grid: refining wins exactly what the skip layer loses
    oracles = oracle_scores(model, frames, batch)
    truth = oracles["truth"][0]
    assert float(truth.clamp(min=0).sum()) > 0 and float(truth.clamp(max=0).sum()) == 0
    config = Config("oracle", model, cfg, budget=budget, oracle="truth")
    seen = []
    ranked = decoder_module.ranked_queries

    def spy(scores, num_dynamic, b):
        seen.append(scores.clone())
        return ranked(scores, num_dynamic, b)
    decoder_module.ranked_queries = spy
    try:
        with torch.no_grad():
            config.decode(frames, batch, new_scene=True, oracles=oracles)
    finally:
        decoder_module.ranked_queries = ranked
    assert len(seen) == 1 and torch.equal(seen[0][0], truth)


def test_auto_under_other_margins(model_and_cfg, capsys):
    """--margins adds auto under each margin: the same needs give each its own rung."""
    model, cfg = model_and_cfg
    configs = {c.name: c for c in configurations(model, cfg, set(), margins=(1.0, 2.0))}
    assert [n for n in configs if n.startswith("auto")] == ["auto", "auto-m1", "auto-m2"]
    # the tiny model's ladder keeps 20 / 12 / 8 static queries: 8 needed fit the smallest
    # rung at margin 1, only the full budget at margin 2 (16 > 12)
    assert [b.static for b in configs["auto"].policy.ladder] == [20, 12, 8]
    assert configs["auto-m1"].policy.covering_level(8, 0) == 2
    assert configs["auto-m2"].policy.covering_level(8, 0) == 0
    with pytest.raises(SystemExit):
        main(["--checkpoint", "x.pt", "--data", "x.pkl", "--out", "x.json", "--margins", "0"])
    assert "--margins" in capsys.readouterr().err
