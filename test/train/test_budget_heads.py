"""Training the query-budget heads (train/budget_heads.py) of a tiny model against its own
full-budget grid: the keep-scores learn which queries the later layers change most, so a
budget that follows them reproduces the full model's grid on unseen inputs better than the
same budget with the ranking reversed or random."""
import torch

from odg_ros.network.budget import budget_of
from odg_ros.train import budget_heads as heads
from testing.helpers import model_inputs, published_grid, tiny_config

TRAIN_SEEDS, TEST_SEEDS = range(10), range(100, 106)


def tiny_model():
    cfg = tiny_config(image_size=(32, 88), num_frames=2, score_threshold=0.0)
    torch.manual_seed(0)
    from odg_ros.network import ODG
    return ODG(cfg).eval(), cfg


def full_grid(model, cfg, inputs):
    with torch.no_grad():
        return published_grid(model(*inputs), cfg)[0][0]


def agreement(model, cfg, budget, seeds, scores=None) -> float:
    """IoU of the budget's grid with the full model's: voxels labelled alike among those
    either calls occupied. ``scores``: replaces the keep-score ranking."""
    budget_heads = model.decoder.budget_heads
    same = either = 0
    for seed in seeds:
        inputs = model_inputs(cfg, seed=seed)
        full = full_grid(model, cfg, inputs)
        if scores is not None:
            learned = budget_heads.scores_of
            budget_heads.scores_of = lambda q, i, d: scores(learned(q, i, d))
        try:
            with torch.no_grad():
                grid = published_grid(model(*inputs, budget=budget), cfg)[0][0]
        finally:
            budget_heads.__dict__.pop("scores_of", None)
        occupied = (full != cfg.num_classes) | (grid != cfg.num_classes)
        same += int(((grid == full) & occupied).sum())
        either += int(occupied.sum())
    return same / either


def test_a_learned_ranking_keeps_what_a_reversed_one_loses(tmp_path):
    model, cfg = tiny_model()
    files = []
    for seed in TRAIN_SEEDS:
        inputs = model_inputs(cfg, seed=seed)
        grid = full_grid(model, cfg, inputs)
        files.append(tmp_path / f"{seed}.pt")
        torch.save(heads.keyframe_record(model, inputs, torch.ones_like(grid)), files[-1])
    heads.init_skip_layer(model)
    heads.fit_skip_layer(model, files, epochs=4, progress=False)
    changes, states = heads.refinement_change(model, files, progress=False)
    heads.fit_keep_scores(model, states, changes, epochs=150, progress=False)
    model.decoder.budget_heads.set_trained(True)
    budget = budget_of(cfg, 0.35)
    generator = torch.Generator().manual_seed(0)
    learned = agreement(model, cfg, budget, TEST_SEEDS)
    reversed_ = agreement(model, cfg, budget, TEST_SEEDS, scores=lambda s: -s)
    random = agreement(model, cfg, budget, TEST_SEEDS,
                       scores=lambda s: torch.rand(s.shape, generator=generator))
    assert learned > reversed_ + 0.03 and learned > random + 0.01


def test_calibration_lowers_an_overconfident_skip_layer(tmp_path):
    """A skip layer made surer than the last layer (every skipped point passes the score
    threshold: floaters) gets the offset that takes it back; agreement with the full grid
    rises with it."""
    from odg_ros.network import ODG
    model, cfg = tiny_model()
    with torch.no_grad():
        scores = model(*model_inputs(cfg, seed=0)).last.logits.sigmoid().amax(-1)
    # an untrained model's scores are all alike: a threshold at their median keeps half
    cfg = tiny_config(image_size=(32, 88), num_frames=2, score_threshold=float(scores.median()))
    torch.manual_seed(0)
    model = ODG(cfg).eval()
    files = []
    for seed in range(3):
        inputs = model_inputs(cfg, seed=seed)
        files.append(tmp_path / f"{seed}.pt")
        mask = torch.ones(cfg.grid_shape, dtype=torch.bool)
        torch.save(heads.keyframe_record(model, inputs, mask), files[-1])
    heads.init_skip_layer(model)
    heads.fit_skip_layer(model, files, epochs=3, progress=False)
    bias = model.decoder.budget_heads.skip_layer.points.cls[-1].bias
    bias.add_(6.0)
    before = bias.clone()
    result = heads.calibrate_skip_layer(model, files, [budget_of(cfg, 0.35)],
                                        offsets=(0.0, 2.0, 4.0, 6.0, 8.0), progress=False)
    agreement = result["agreement"]
    assert result["offset"] >= 4.0
    assert agreement[result["offset"]] > agreement[0.0] + 1.0
    assert torch.equal(bias, before - result["offset"])
