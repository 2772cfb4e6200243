"""Focal loss, Hungarian matching and the box loss against hand-checked float64 values."""
import math

import pytest
import torch

from odg_ros.losses.box import (BOX_CODE_WEIGHTS, box_loss, check_gt_boxes, decode_boxes,
                                encode_boxes)
from odg_ros.losses.focal import one_hot_targets, sigmoid_focal_loss
from odg_ros.losses.matcher import (NONFINITE_COST, box_match_cost, focal_match_cost,
                                    hungarian_match)


def focal_reference(x: float, t: float, alpha=0.25, gamma=2.0) -> float:
    p = 1 / (1 + math.exp(-x))
    return -(alpha * t * (1 - p) ** gamma * math.log(p)
             + (1 - alpha) * (1 - t) * p ** gamma * math.log(1 - p))


# --- focal ----------------------------------------------------------------------------------

def test_focal_matches_formula_float64():
    x = torch.tensor([[-3.0, -0.5, 0.0, 0.7, 4.0]], dtype=torch.float64).repeat(2, 1)
    t = torch.zeros_like(x)
    t[0] = 1
    got = sigmoid_focal_loss(x, t)
    for i in range(2):
        for j in range(5):
            assert got[i, j].item() == pytest.approx(focal_reference(x[i, j].item(), t[i, j].item()),
                                                     rel=1e-12)


def test_focal_extreme_logits_finite_with_finite_gradients():
    x = torch.tensor([[100.0, -100.0, 100.0, -100.0]], requires_grad=True)
    t = torch.tensor([[1.0, 0.0, 0.0, 1.0]])
    loss = sigmoid_focal_loss(x, t)
    assert torch.isfinite(loss).all()
    assert loss[0, 0] < 1e-30 and loss[0, 1] < 1e-30          # confident and right: ~0
    assert loss[0, 2].item() == pytest.approx(0.75 * 100, rel=1e-6)   # confident and wrong
    assert loss[0, 3].item() == pytest.approx(0.25 * 100, rel=1e-6)
    loss.sum().backward()
    assert torch.isfinite(x.grad).all()


def test_focal_gradcheck():
    x = torch.randn(3, 4, dtype=torch.float64, requires_grad=True)
    t = one_hot_targets(torch.tensor([0, -1, 3]), 4, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda v: sigmoid_focal_loss(v, t), (x,))


def test_one_hot_background_rows_are_zero():
    t = one_hot_targets(torch.tensor([2, -1, 5, 0]), 4)
    assert t.tolist() == [[0, 0, 1, 0], [0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0]]


# --- matcher --------------------------------------------------------------------------------

def test_hungarian_two_by_two_known_optimum():
    rows, cols, bad = hungarian_match(torch.tensor([[4.0, 1.0], [2.0, 6.0]]))
    assert dict(zip(rows.tolist(), cols.tolist())) == {0: 1, 1: 0} and bad == 0
    rows, cols, _ = hungarian_match(torch.tensor([[1.0, 3.0], [4.0, 2.0]]))   # 1+2 = 3 < 3+4
    assert dict(zip(rows.tolist(), cols.tolist())) == {0: 0, 1: 1}


def test_hungarian_more_predictions_than_gt_and_empty():
    rows, cols, _ = hungarian_match(torch.tensor([[5.0], [0.5], [3.0]]))
    assert rows.tolist() == [1] and cols.tolist() == [0]
    rows, cols, bad = hungarian_match(torch.zeros(4, 0))
    assert rows.numel() == cols.numel() == 0 and bad == 0


def test_hungarian_nan_inf_replaced_and_counted():
    cost = torch.tensor([[float("nan"), 1.0], [2.0, float("inf")]])
    rows, cols, bad = hungarian_match(cost)
    assert bad == 2
    assert dict(zip(rows.tolist(), cols.tolist())) == {0: 1, 1: 0}
    rows, cols, bad = hungarian_match(torch.full((2, 2), float("nan")))   # all bad: still a match
    assert bad == 4 and sorted(cols.tolist()) == [0, 1]
    assert NONFINITE_COST > 1e5


def test_focal_match_cost_formula_and_extremes():
    logits = torch.tensor([[0.3, -1.2], [100.0, -100.0]], dtype=torch.float64)
    cost = focal_match_cost(logits, torch.tensor([1, 0]))
    for i in range(2):
        for j, c in enumerate([1, 0]):
            p = torch.sigmoid(logits[i, c]).item()
            pos = 0.25 * (1 - p) ** 2 * -math.log(max(p, 1e-300))
            neg = 0.75 * p ** 2 * -math.log(max(1 - p, 1e-300))
            if abs(logits[i, c]) < 50:
                assert cost[i, j].item() == pytest.approx(pos - neg, rel=1e-10)
    assert torch.isfinite(cost).all()
    assert cost[1, 1] < cost[0, 1]          # a confident right class costs less


def test_box_match_cost_l1_ignores_nan_velocity():
    codes = torch.zeros(1, 10)
    gt = torch.zeros(1, 10)
    gt[0, 0] = 1.0
    gt[0, 8:] = float("nan")
    logits = torch.zeros(1, 3)
    cost = box_match_cost(codes, logits, gt, torch.tensor([0]), BOX_CODE_WEIGHTS)
    expected = 2.0 * focal_match_cost(logits, torch.tensor([0]))[0, 0] + 0.25 * 2.0 * 1.0
    assert cost[0, 0].item() == pytest.approx(expected.item(), rel=1e-6)


# --- box code -------------------------------------------------------------------------------

def test_box_code_round_trip_and_fields():
    g = torch.Generator().manual_seed(1)
    boxes = torch.cat([torch.rand(50, 3, generator=g) * 80 - 40,
                       torch.rand(50, 3, generator=g) * 10 + 0.1,
                       (torch.rand(50, 1, generator=g) * 2 - 1) * math.pi * 0.999,
                       torch.randn(50, 2, generator=g)], dim=1).double()
    code = encode_boxes(boxes)
    assert torch.allclose(code[:, 3:6], boxes[:, 3:6].log())
    assert torch.allclose(code[:, 6], boxes[:, 6].sin()) and torch.allclose(code[:, 7], boxes[:, 6].cos())
    assert torch.allclose(decode_boxes(code), boxes, atol=1e-12)
    wrapped = boxes.clone()
    wrapped[:, 6] += 2 * math.pi                       # yaw comes back in (-pi, pi]
    assert torch.allclose(decode_boxes(encode_boxes(wrapped)), boxes, atol=1e-9)


def test_gt_box_validation():
    good = torch.tensor([[0, 0, 0, 1, 2, 1.5, 0.3, float("nan"), float("nan")]])
    check_gt_boxes(good, torch.tensor([0]), 10)        # missing velocity is allowed
    with pytest.raises(ValueError, match="size"):
        check_gt_boxes(good * torch.tensor([1, 1, 1, 0, 1, 1, 1, 1, 1]), torch.tensor([0]), 10)
    with pytest.raises(ValueError, match="labels"):
        check_gt_boxes(good, torch.tensor([10]), 10)
    bad = good.clone()
    bad[0, 0] = float("inf")
    with pytest.raises(ValueError, match="non-finite"):
        check_gt_boxes(bad, torch.tensor([0]), 10)


# --- box loss -------------------------------------------------------------------------------

def _box(cx, cy, yaw=0.0, vx=0.0):
    return [cx, cy, 0.5, 2.0, 4.0, 1.5, yaw, vx, 0.0]


def test_box_loss_hand_checked():
    gt = torch.tensor([_box(10.0, 0.0), _box(-5.0, 3.0)])
    labels = torch.tensor([0, 8])
    codes = encode_boxes(torch.tensor([_box(-5.0, 3.5), _box(9.0, 0.0), _box(30.0, 30.0)]))[None]
    logits = torch.full((1, 3, 10), -4.0)
    codes.requires_grad_(True)
    logits.requires_grad_(True)
    res = box_loss(codes, logits, [gt], [labels])
    assert res.num_matched == 2
    # pred 0 <-> gt 1 (|dy| = 0.5, weight 2), pred 1 <-> gt 0 (|dx| = 1, weight 2)
    assert res.l1.item() == pytest.approx(0.25 * (2 * 0.5 + 2 * 1.0) / 2, rel=1e-6)
    # focal: all 30 logits are -4; two of them (pred0/class 8, pred1/class 0) are positives
    expected = (2 * focal_reference(-4.0, 1.0) + 28 * focal_reference(-4.0, 0.0)) / 2
    assert res.focal.item() == pytest.approx(2.0 * expected, rel=1e-5)
    (res.l1 + res.focal).backward()
    assert torch.isfinite(codes.grad).all() and torch.isfinite(logits.grad).all()
    assert codes.grad[0, 2].abs().sum() == 0          # unmatched prediction gets no L1 gradient


def test_box_loss_normaliser_is_the_mean_matched_count_over_ddp_processes(monkeypatch):
    """Under DDP (two processes: this one matched 2 boxes, the other 6) the loss is divided
    by the mean count 4, not by this process's 2 (DETR), so DDP's gradient average weighs
    every box alike; an all-reduce that finds no box anywhere still divides by 1."""
    from odg_ros.losses import box as box_module
    gt = torch.tensor([_box(10.0, 0.0), _box(-5.0, 3.0)])
    labels = torch.tensor([0, 8])
    codes = encode_boxes(torch.tensor([_box(-5.0, 3.5), _box(9.0, 0.0), _box(30.0, 30.0)]))[None]
    logits = torch.full((1, 3, 10), -4.0)
    alone = box_loss(codes, logits, [gt], [labels])
    other_process = {"matched": 6.0}

    def all_reduce(tensor):
        tensor += other_process["matched"]
    monkeypatch.setattr(box_module.dist, "is_initialized", lambda: True)
    monkeypatch.setattr(box_module.dist, "get_world_size", lambda: 2)
    monkeypatch.setattr(box_module.dist, "all_reduce", all_reduce)
    shared = box_loss(codes, logits, [gt], [labels])
    assert shared.num_matched == 2
    assert shared.l1.item() == pytest.approx(alone.l1.item() * 2 / 4, rel=1e-6)
    assert shared.focal.item() == pytest.approx(alone.focal.item() * 2 / 4, rel=1e-6)
    other_process["matched"] = 0.0
    empty = box_loss(codes, logits, [gt[:0]], [labels[:0]])
    assert torch.isfinite(empty.focal) and empty.l1.item() == 0.0


def test_box_loss_no_gt_is_focal_on_all_negatives():
    codes = torch.randn(2, 4, 10, requires_grad=True)
    logits = torch.randn(2, 4, 10, requires_grad=True)
    res = box_loss(codes, logits, [torch.zeros(0, 9)] * 2, [torch.zeros(0, dtype=torch.long)] * 2)
    assert res.num_matched == 0 and res.l1.item() == 0
    expected = 2.0 * sigmoid_focal_loss(logits.detach(), torch.zeros(2, 4, 10)).sum()  # norm 1
    assert res.focal.item() == pytest.approx(expected.item(), rel=1e-6)
    (res.l1 + res.focal).backward()
    assert codes.grad is None                          # no box is supervised
    assert torch.isfinite(logits.grad).all()


def test_box_loss_nan_velocity_ignored_and_counted():
    gt = torch.tensor([_box(1.0, 1.0)])
    gt[0, 7:] = float("nan")
    codes = encode_boxes(torch.tensor([_box(1.0, 1.0, vx=3.0)]))[None].requires_grad_(True)
    res = box_loss(codes, torch.zeros(1, 1, 10), [gt], [torch.tensor([3])])
    assert res.num_nonfinite_targets == 2
    assert res.l1.item() == 0                          # velocity not supervised, rest exact
    res.l1.backward()
    assert torch.isfinite(codes.grad).all()


def test_box_loss_nan_prediction_cost_counted():
    codes = torch.zeros(1, 2, 10)
    codes[0, 0, 0] = float("nan")
    res = box_loss(codes, torch.zeros(1, 2, 10), [torch.tensor([_box(0.0, 0.0)])],
                   [torch.tensor([1])])
    assert res.num_nonfinite_costs == 1 and res.num_matched == 1
    assert torch.isfinite(res.l1)                     # matched to the finite prediction


def test_box_loss_matches_float64_bruteforce_on_random():
    g = torch.Generator().manual_seed(3)
    D, M, C = 5, 3, 10
    gt = torch.cat([torch.rand(M, 3, generator=g) * 20, torch.rand(M, 3, generator=g) * 3 + 0.5,
                    torch.rand(M, 1, generator=g) * 6 - 3, torch.randn(M, 2, generator=g)], 1)
    labels = torch.randint(0, C, (M,), generator=g)
    codes = torch.randn(1, D, 10, generator=g) * 3
    logits = torch.randn(1, D, C, generator=g)
    res = box_loss(codes, logits, [gt], [labels])
    # brute force over all injective assignments, in float64
    import itertools
    gc = encode_boxes(gt.double())
    w = torch.tensor(BOX_CODE_WEIGHTS, dtype=torch.float64)
    best = None
    for perm in itertools.permutations(range(D), M):
        cost = 0.0
        for j, i in enumerate(perm):
            cost += 2.0 * focal_match_cost(logits[0, i:i + 1].double(), labels[j:j + 1])[0, 0].item()
            cost += 0.25 * ((codes[0, i].double() - gc[j]).abs() * w).sum().item()
        if best is None or cost < best[0]:
            best = (cost, perm)
    perm = best[1]
    l1 = sum(((codes[0, i].double() - gc[j]).abs() * w).sum().item() for j, i in enumerate(perm))
    t = torch.zeros(D, C, dtype=torch.float64)
    for j, i in enumerate(perm):
        t[i, labels[j]] = 1
    focal = sigmoid_focal_loss(logits[0].double(), t).sum().item()
    assert res.l1.item() == pytest.approx(0.25 * l1 / M, rel=1e-5)
    assert res.focal.item() == pytest.approx(2.0 * focal / M, rel=1e-5)


def test_box_loss_gradcheck_float64():
    gt = torch.tensor([_box(1.0, 2.0, yaw=0.4, vx=1.0), _box(-3.0, 0.5)], dtype=torch.float64)
    codes = (encode_boxes(gt) + 0.3 * torch.randn(2, 10, dtype=torch.float64))[None]
    codes = torch.cat([codes, torch.randn(1, 1, 10, dtype=torch.float64)], 1).requires_grad_(True)
    logits = torch.randn(1, 3, 10, dtype=torch.float64, requires_grad=True)

    def f(c, x):
        res = box_loss(c, x, [gt], [torch.tensor([0, 4])])
        return res.l1 + res.focal

    assert torch.autograd.gradcheck(f, (codes, logits))
