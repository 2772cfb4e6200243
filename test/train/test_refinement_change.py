"""The keep-score target (train/budget_heads.py): how much refining a query changes its part
of the grid, weighted by what a voxel of each class is worth to the keyframe's mIoU. Checked
against a point-by-point reference on random outputs and on hand-made cases."""
import itertools

import numpy as np
import pytest
import torch

from odg_ros.train import budget_heads as heads
from testing.helpers import tiny_config

CFG = tiny_config()


def random_output(generator, queries=12, points=6, classes=None):
    """(means [Q, K, 3] spread over a few voxels near the ego, logits [Q, K, C])."""
    C = classes or CFG.num_classes
    centre = torch.rand(queries, 1, 3, generator=generator) * torch.tensor([6.0, 6.0, 2.0])
    means = centre + 0.6 * torch.randn(queries, points, 3, generator=generator)
    logits = 3 * torch.randn(queries, points, C, generator=generator)
    return means, logits


def reference_pairs(means, logits, mask):
    """Point by point, as postprocess.voxelise keeps points -> {query: {(voxel, class)}}."""
    X, Y, Z = CFG.grid_shape
    pairs = {}
    for q, k in itertools.product(range(means.shape[0]), range(means.shape[1])):
        point, scores = means[q, k].double(), logits[q, k].double().sigmoid()
        centroid = means[q].double().mean(dim=0)
        if scores.max() <= CFG.score_threshold or \
                (point - centroid).norm() > CFG.max_distance_to_centroid:
            continue
        index = [int(np.floor((float(point[a]) - CFG.pc_range[a]) / CFG.voxel_size))
                 for a in range(3)]
        if not all(0 <= i < n for i, n in zip(index, (X, Y, Z))) or not mask[tuple(index)]:
            continue
        voxel = (index[0] * Y + index[1]) * Z + index[2]
        pairs.setdefault(q, set()).add((voxel, int(scores.argmax())))
    return pairs


@pytest.mark.parametrize("seed", range(4))
def test_output_change_counts_the_pairs_one_output_has_and_the_other_not(seed):
    generator = torch.Generator().manual_seed(seed)
    full, skipped = random_output(generator), random_output(generator)
    mask = torch.rand(CFG.grid_shape, generator=generator) > 0.2
    weights = torch.rand(CFG.num_classes, generator=generator) + 0.1
    got = heads.output_change(full, skipped, mask, weights, CFG)
    a, b = reference_pairs(*full, mask), reference_pairs(*skipped, mask)
    expected = [sum(float(weights[c]) for _, c in a.get(q, set()) ^ b.get(q, set()))
                for q in range(len(full[0]))]
    assert got.tolist() == pytest.approx(expected, rel=1e-6, abs=1e-6)
    assert sum(expected) > 0                       # the case is not empty


def test_an_unchanged_query_costs_nothing_and_a_moved_one_both_voxels():
    generator = torch.Generator().manual_seed(0)
    means, logits = random_output(generator)
    moved = means.clone()
    moved[3] += torch.tensor([CFG.voxel_size * 3, 0.0, 0.0])   # a whole query, 3 voxels on
    mask = torch.ones(CFG.grid_shape, dtype=torch.bool)
    weights = torch.ones(CFG.num_classes)
    change = heads.output_change((means, logits), (moved, logits), mask, weights, CFG)
    assert heads.output_change((means, logits), (means, logits), mask, weights, CFG).eq(0).all()
    pairs = reference_pairs(means, logits, mask)[3]
    assert change[3] == 2 * len(pairs) and change.sum() == change[3]


def test_a_voxel_of_a_rare_class_is_worth_more_than_one_of_a_common_class():
    """Class 0 fills 300 voxels of the full output, class 1 one: a voxel of class 1 is worth
    (300 + floor) / (1 + floor) times as much; classes absent count from the floor."""
    X, Y, Z = CFG.grid_shape
    cells = torch.stack(torch.meshgrid(torch.arange(30), torch.arange(10), torch.tensor([0]),
                                       indexing="ij"), -1).reshape(-1, 3).float()
    cells = torch.cat([cells, torch.tensor([[40.0, 40.0, 2.0]])])      # the one class-1 voxel
    means = torch.tensor(CFG.pc_range[:3]) + (cells + 0.5) * CFG.voxel_size
    logits = torch.full((len(cells), 1, CFG.num_classes), -9.0)
    logits[:-1, 0, 0] = logits[-1, 0, 1] = 9.0
    weights = heads.keyframe_class_weights(means[:, None], logits,
                                           torch.ones(X, Y, Z, dtype=torch.bool), CFG)
    scale, floor = heads.CLASS_WEIGHT_SCALE, heads.CLASS_WEIGHT_FLOOR
    assert weights[0] == pytest.approx(scale / (300 + floor))
    assert weights[1] == pytest.approx(scale / (1 + floor))
    assert weights[2] == pytest.approx(scale / floor)


@pytest.mark.parametrize("seed", range(3))
def test_ground_truth_gain_counts_the_correct_pairs_won_against_a_reference(seed):
    generator = torch.Generator().manual_seed(seed)
    full, skipped = random_output(generator), random_output(generator)
    mask = torch.rand(CFG.grid_shape, generator=generator) > 0.2
    # ground truth: random, with half of each output's pairs made correct (the skipped
    # output's last, so that both outputs win and lose some)
    semantics = torch.randint(0, CFG.num_classes + 1, CFG.grid_shape, generator=generator)
    flat = semantics.view(-1)
    for output in (full, skipped):
        for q, pairs in reference_pairs(*output, mask).items():
            for voxel, label in sorted(pairs)[q % 2::2]:
                flat[voxel] = label
    got = heads.ground_truth_gain(full, skipped, semantics, mask, CFG)
    counts = np.bincount(semantics[mask].numpy(), minlength=CFG.num_classes + 1)
    weight = [heads.CLASS_WEIGHT_SCALE / (counts[c] + heads.CLASS_WEIGHT_FLOOR)
              for c in range(CFG.num_classes)]

    def correct(pairs, q):
        return sum(weight[c] for v, c in pairs.get(q, set()) if int(flat[v]) == c)
    a, b = reference_pairs(*full, mask), reference_pairs(*skipped, mask)
    expected = [correct(a, q) - correct(b, q) for q in range(len(full[0]))]
    assert got.tolist() == pytest.approx(expected, rel=1e-6, abs=1e-6)
    assert any(e > 0 for e in expected) and any(e < 0 for e in expected)
