"""Hard cases of the losses: empty GT and empty predictions, every prediction on one GT voxel,
Hungarian costs with NaN / +-inf / huge finite entries, focal loss at logits up to +-1e4,
class weights with absent (or zero-weight) classes, and the whole criterion on combinations
of empty and extreme inputs.

Already covered elsewhere (not repeated): test_loss_focal_box.py (focal at +-100, NaN/inf
costs replaced and counted, NaN GT velocity), test_loss_chamfer.py (no GT voxel, NaN points
raise), test_loss_criterion.py (empty batch, NaN output names the term),
test_loss_render.py (no LiDAR pixel).
"""
import itertools
import math

import numpy as np
import pytest
import torch
from hypothesis import assume, given
from hypothesis import strategies as st

from odg_ros.classes import OCC_CLASS_WEIGHTS
from odg_ros.losses import ODGCriterion, box_loss, occupancy_loss, occupancy_target
from odg_ros.losses.focal import sigmoid_focal_loss
from odg_ros.losses.matcher import NONFINITE_COST, focal_match_cost, hungarian_match

from testing.hard_cases import FEW, HARD, all_finite
from testing.losses import reference_occupancy
from testing.losses import CFG, all_output_tensors, make_batch, make_output

RANGE = (-2.0, -2.0, -1.0, 2.0, 2.0, 0.6)          # a 10 x 10 x 4 grid of 0.4 m voxels


def grid_target(voxels, labels=None, visible=True):
    """GT with the given occupied (i, j, k) voxels."""
    sem = torch.full((10, 10, 4), 17, dtype=torch.uint8)
    for n, ijk in enumerate(voxels):
        sem[ijk] = 4 if labels is None else labels[n]
    mask = torch.full_like(sem, visible, dtype=torch.bool)
    return occupancy_target(sem, mask, RANGE, 0.4)


# ------------------------------------------------------------------------------ Chamfer
@HARD
@given(num_points=st.integers(1, 40), other_voxels=st.integers(0, 30),
       voxel=st.tuples(st.integers(0, 9), st.integers(0, 9), st.integers(0, 3)))
def test_every_prediction_on_one_gt_voxel(num_points, other_voxels, voxel):
    rng = np.random.default_rng(num_points * 100 + other_voxels)
    others = {tuple(v) for v in rng.integers([0, 0, 0], [10, 10, 4], (other_voxels, 3))}
    others.discard(voxel)
    target = grid_target([voxel] + sorted(others))
    centre = (torch.tensor(voxel, dtype=torch.float32) + 0.5) * 0.4 + torch.tensor(RANGE[:3])
    points = centre.expand(1, num_points, 3).clone().requires_grad_(True)
    logits = torch.zeros(1, num_points, 17, requires_grad=True)
    out = occupancy_loss(points, logits, [target], RANGE)
    assert all_finite(out.chamfer, out.focal)
    grads = torch.autograd.grad(out.chamfer + out.focal, [points, logits])
    assert all_finite(*grads)
    if not others:                        # the only GT voxel is covered exactly: no pull at all
        assert out.chamfer == 0 and grads[0].abs().max() == 0
    chamfer, focal = reference_occupancy(points[0].detach(), logits[0].detach(),
                                         target.centres, target.labels, target.visible, RANGE)
    torch.testing.assert_close(out.chamfer.double(), chamfer, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out.focal.double(), focal, rtol=1e-5, atol=1e-6)


def test_empty_predictions_against_gt_is_a_clear_error():
    target = grid_target([(3, 3, 1), (4, 3, 1)])
    with pytest.raises(ValueError, match="no predicted points"):
        occupancy_loss(torch.zeros(1, 0, 3), torch.zeros(1, 0, 17), [target], RANGE)


def test_empty_predictions_and_empty_gt_are_zero():
    out = occupancy_loss(torch.zeros(2, 0, 3, requires_grad=True), torch.zeros(2, 0, 17),
                         [grid_target([]), grid_target([])], RANGE)
    assert out.chamfer == 0 and out.focal == 0 and out.num_samples_without_gt == 2


def test_empty_box_predictions_and_empty_box_gt():
    codes, logits = torch.zeros(1, 0, 10, requires_grad=True), torch.zeros(1, 0, 10)
    gt = [torch.tensor([[1.0, 2.0, 0.5, 2.0, 4.0, 1.5, 0.3, 1.0, 0.0]])]
    out = box_loss(codes, logits, gt, [torch.tensor([3])])
    assert out.l1 == 0 and out.focal == 0 and out.num_matched == 0
    out = box_loss(torch.randn(1, 4, 10), torch.randn(1, 4, 10), [torch.zeros(0, 9)],
                   [torch.zeros(0, dtype=torch.long)])
    assert out.l1 == 0 and math.isfinite(out.focal) and out.focal > 0


@pytest.mark.parametrize("weights", ["absent class weighted 0", "present class weighted 0",
                                     "every class weighted 0"])
def test_class_weights_with_absent_and_zero_weight_classes(weights):
    """GT has cars (4) and road (11) only. Absent classes get negative targets only, so
    their logits are pushed down (gradient > 0) unless their weight is 0 (gradient 0)."""
    target = grid_target([(2, 2, 1), (7, 7, 0)], labels=[4, 11])
    w = list(OCC_CLASS_WEIGHTS)
    if weights == "absent class weighted 0":
        w[7] = 0.0
    elif weights == "present class weighted 0":
        w[4] = 0.0
    else:
        w = [0.0] * 17
    points = torch.tensor([[[-1.0, -1.0, -0.4], [1.0, 1.0, -0.8]]], requires_grad=True)
    logits = torch.zeros(1, 2, 17, requires_grad=True)
    out = occupancy_loss(points, logits, [target], RANGE, class_weights=w)
    assert all_finite(out.chamfer, out.focal)
    (grad,) = torch.autograd.grad(out.focal, logits)
    assert torch.isfinite(grad).all()
    for c in range(17):
        if w[c] == 0:
            assert grad[0, :, c].abs().max() == 0
        elif c not in (4, 11):
            assert (grad[0, :, c] > 0).all()
    if weights == "every class weighted 0":
        assert out.focal == 0


# ------------------------------------------------------------------------------ Hungarian
COSTS = st.floats(-50, 50) | st.sampled_from([0.0, 1e7, 1e12, math.nan, math.inf, -math.inf])


@HARD
@given(shape=st.tuples(st.integers(1, 5), st.integers(1, 5)), data=st.data())
def test_hungarian_never_prefers_a_nonfinite_pair(shape, data):
    """Whenever a full assignment of finite costs exists, the matcher returns one, and the
    cheapest such (brute force); NaN/inf costs are counted. Finite costs may exceed
    NONFINITE_COST (a diverging box code): a NaN pair must still not look cheaper."""
    D, M = shape
    cost = torch.tensor([[data.draw(COSTS) for _ in range(M)] for _ in range(D)],
                        dtype=torch.float64)
    rows, cols, bad = hungarian_match(cost)
    K = min(D, M)
    assert len(rows) == len(cols) == K
    assert len(set(rows.tolist())) == K and len(set(cols.tolist())) == K
    assert bad == int((~torch.isfinite(cost)).sum())
    finite = torch.isfinite(cost)
    best = None
    small, large = (range(D), range(M)) if D <= M else (range(M), range(D))
    for perm in itertools.permutations(large, K):
        pairs = list(zip(small, perm)) if D <= M else [(p, s) for s, p in zip(small, perm)]
        if all(finite[r, c] for r, c in pairs):
            total = sum(float(cost[r, c]) for r, c in pairs)
            best = total if best is None else min(best, total)
    if best is not None:
        assert finite[rows, cols].all()
        chosen = float(cost[rows, cols].sum())
        assert chosen <= best + 1e-9 * max(1.0, abs(best))


def test_hungarian_all_nonfinite():
    cost = torch.tensor([[math.nan, math.inf], [-math.inf, math.nan]])
    rows, cols, bad = hungarian_match(cost)
    assert bad == 4 and sorted(rows.tolist()) == [0, 1] and sorted(cols.tolist()) == [0, 1]
    assert NONFINITE_COST > 0


# ------------------------------------------------------------------------------ focal
def focal_reference(x, t, alpha=0.25, gamma=2.0):
    """float64 NumPy, log-sigmoid form (exact for any finite x)."""
    x, t = np.asarray(x, dtype=np.float64), np.asarray(t, dtype=np.float64)
    log_p = -np.logaddexp(0.0, -x)            # log sigmoid(x)
    log_q = -np.logaddexp(0.0, x)             # log sigmoid(-x) = log(1 - p)
    bce = -(t * log_p + (1 - t) * log_q)
    p_t = t * np.exp(log_q) + (1 - t) * np.exp(log_p)
    return bce * (alpha * t + (1 - alpha) * (1 - t)) * p_t ** gamma


LOGITS = st.sampled_from([0.0, 16.6, 17.0, 88.7, 89.0, 100.0, 103.0, 1e4, -1e4, -100.0,
                          -88.7, -17.0]) | st.floats(-1e4, 1e4)


@HARD
@given(logits=st.lists(LOGITS, min_size=1, max_size=8), data=st.data(),
       dtype=st.sampled_from([torch.float32, torch.float64]))
def test_focal_loss_at_extreme_logits_matches_the_exact_reference(logits, data, dtype):
    targets = data.draw(st.lists(st.sampled_from([0.0, 1.0]), min_size=len(logits),
                                 max_size=len(logits)))
    x = torch.tensor(logits, dtype=dtype, requires_grad=True)
    t = torch.tensor(targets, dtype=dtype)
    loss = sigmoid_focal_loss(x, t)
    assert torch.isfinite(loss).all() and (loss >= 0).all()
    (grad,) = torch.autograd.grad(loss.sum(), x)
    assert torch.isfinite(grad).all()
    expected = focal_reference(x.detach().double().numpy(), targets)
    # torch's BCE-with-logits takes log(1 + e^-|x|) without log1p: on the easy side of
    # |x| > 15 (float64) / 8 (float32) the term loses its relative precision (0 from
    # |x| ~ 37 / 17); the absolute error stays below 1e-12, nothing next to O(1) terms
    np.testing.assert_allclose(loss.detach().double().numpy(), expected, rtol=2e-5,
                               atol=1e-12)
    cost = focal_match_cost(x.detach()[:, None], torch.zeros(1, dtype=torch.long))
    assert torch.isfinite(cost).all()


def test_focal_loss_in_bfloat16_stays_finite():
    x = torch.tensor([-1e4, -100.0, -17.0, 0.0, 17.0, 100.0, 1e4], dtype=torch.bfloat16,
                     requires_grad=True)
    for t in (torch.zeros_like(x), torch.ones_like(x)):
        loss = sigmoid_focal_loss(x, t)
        assert torch.isfinite(loss).all()
        assert torch.isfinite(torch.autograd.grad(loss.sum(), x)[0]).all()


# ------------------------------------------------------------------------------ criterion
def scaled_output(scale, collapse, seed):
    out = make_output(seed=seed)
    with torch.no_grad():
        for layer in out.layers:
            layer.logits.mul_(scale)
            layer.box_logits.mul_(scale)
            if collapse:                      # every mean on one voxel centre of the car
                layer.means.copy_(torch.tensor([6.2, 0.2, 0.2]).expand_as(layer.means))
    return out


@FEW
@given(occupied=st.booleans(), boxes=st.booleans(), lidar=st.booleans(),
       scale=st.sampled_from([1.0, 100.0]), collapse=st.booleans())
def test_criterion_on_empty_and_extreme_combinations(occupied, boxes, lidar, scale, collapse):
    """Empty GT grid / no GT box / no LiDAR pixel, logits of +-100s, all means on one voxel,
    in every combination: every term finite, gradients finite."""
    out = scaled_output(scale, collapse, seed=int(occupied) + 2 * int(boxes))
    criterion = ODGCriterion(CFG, render_pixels_per_camera=16)
    losses = criterion(out, make_batch(occupied=occupied, boxes=boxes, lidar=lidar))
    assert all(torch.isfinite(v).all() for v in losses.values())
    tensors = all_output_tensors(out)
    grads = torch.autograd.grad(losses["loss"], tensors, allow_unused=True)
    assert all_finite(*grads)


@pytest.mark.parametrize("bad", [math.inf, -math.inf])
def test_criterion_with_an_infinite_logit_names_the_term(bad):
    out = make_output()
    with torch.no_grad():
        out.layers[2].logits[0, 0, 0, 3] = bad
    with pytest.raises(FloatingPointError, match="occ_focal_l3"):
        ODGCriterion(CFG, render=False)(out, make_batch())
