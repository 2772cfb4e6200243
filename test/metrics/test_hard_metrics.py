"""Hard cases of the metrics: empty classes, all-free grids, ray origins on voxel corners /
edges / faces (in voxel units and in metres), rays exactly along the axes and the lattice
diagonals, rays tilted by 1e-12 off an axis.

Already covered by test_rayiou.py / test_miou.py (fixed cases, not repeated): a corner origin
with diagonal rays, axis-parallel rays from a voxel centre, a face origin, a class predicted
but absent from the GT, an all-free prediction, no origins. Here hypothesis draws the
combinations and the fast traversal is compared ray by ray with the scalar transcription of
SparseOcc's caster (testing/sparseocc_reference.py).
"""
import math
import warnings

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from odg_ros.metrics.miou import MIoU
from odg_ros.metrics.raycast import cast_rays
from odg_ros.metrics.rayiou import RayIoU

from testing.hard_cases import FEW, HARD
from testing.sparseocc_reference import render_forward_one_ray, sparseocc_rayiou
from testing.metrics import rays_from, unravel

AXES = [tuple(float(s) * e for e in np.eye(3)[a]) for a in range(3) for s in (1, -1)]
DIAGONALS = [tuple(np.array([sx, sy, sz]) / math.sqrt(abs(sx) + abs(sy) + abs(sz)))
             for sx in (-1, 0, 1) for sy in (-1, 0, 1) for sz in (-1, 0, 1)
             if abs(sx) + abs(sy) + abs(sz) >= 2]


def tilted(axis_index, sign, tilt):
    d = np.zeros(3)
    d[axis_index] = sign
    d[(axis_index + 1) % 3] = tilt
    return tuple(d / np.linalg.norm(d))


directions = (st.sampled_from(AXES + DIAGONALS)
              | st.builds(tilted, st.integers(0, 2), st.sampled_from([1.0, -1.0]),
                          st.sampled_from([1e-12, -1e-12, 1e-16])))


@st.composite
def lattice_origin(draw, shape):
    """A point with integer (corner), half-integer or arbitrary coordinates per axis, on the
    grid boundary or one voxel outside it included."""
    coords = []
    for n in shape:
        kind = draw(st.sampled_from(["corner", "centre", "any"]))
        if kind == "corner":
            coords.append(float(draw(st.integers(-1, n + 1))))
        elif kind == "centre":
            coords.append(draw(st.integers(0, n - 1)) + 0.5)
        else:
            coords.append(draw(st.floats(-1.0, n + 1.0)))
    return tuple(coords)


@HARD
@given(data=st.data(), shape=st.tuples(st.integers(2, 7), st.integers(2, 7), st.integers(2, 5)),
       density=st.sampled_from([0.0, 0.1, 0.3, 1.0]))
def test_rays_from_lattice_points_match_sparseocc(data, shape, density):
    rng = np.random.default_rng(int(np.prod(shape) * 10 + density * 10))
    occupied = rng.random(shape) < density
    origins = [data.draw(lattice_origin(shape)) for _ in range(4)]
    dirs = [data.draw(directions) for _ in range(6)]
    start, end = rays_from(origins, dirs)
    index, depth = cast_rays(occupied.astype(np.uint8), start, end)
    # (a depth can be negative: an origin just below the grid truncates into voxel 0)
    assert np.isfinite(depth).all()
    grid = occupied.tolist()
    for r in range(len(start)):
        ref_depth, ref_voxel = render_forward_one_ray(grid, start[r], end[r])
        assert unravel(index[0, r], shape) == ref_voxel, (start[r], end[r])
        assert depth[0, r] == ref_depth, (start[r], end[r])


def no_warnings():
    ctx = warnings.catch_warnings()
    ctx.__enter__()
    warnings.simplefilter("error")          # e.g. numpy's "Mean of empty slice"
    return ctx


@HARD
@given(classes=st.lists(st.integers(0, 17), min_size=1, max_size=4, unique=True),
       pred_classes=st.lists(st.integers(0, 17), min_size=1, max_size=4, unique=True),
       masked=st.booleans())
def test_miou_with_absent_classes_matches_a_direct_count(classes, pred_classes, masked):
    rng = np.random.default_rng(len(classes) * 31 + len(pred_classes))
    gt = rng.choice(classes, size=(6, 5, 3))
    pred = rng.choice(pred_classes, size=(6, 5, 3))
    mask = rng.random((6, 5, 3)) < 0.5 if masked else None
    metric = MIoU()
    ctx = no_warnings()
    try:
        metric.add(pred, gt, mask)
        result = metric.result()
    finally:
        ctx.__exit__(None, None, None)
    keep = np.ones(gt.shape, bool) if mask is None else mask
    g, p = gt[keep], pred[keep]
    for c in range(17):
        tp = np.sum((g == c) & (p == c))
        union = np.sum((g == c) | (p == c))
        if not (g == c).any():
            assert math.isnan(result["per_class"][c])      # absent from the GT: NaN
        else:
            assert result["per_class"][c] == pytest.approx(tp / union)
    present = [c for c in range(17) if (g == c).any()]
    if present:
        assert result["mIoU"] == pytest.approx(np.mean([result["per_class"][c] for c in present]))
    else:
        assert math.isnan(result["mIoU"])


@pytest.mark.parametrize("metric_kind", ["miou", "rayiou"])
def test_all_free_grids_give_nan_without_warnings_or_errors(metric_kind):
    free = np.full((200, 200, 16), 17, dtype=np.uint8)
    occupied = free.copy()
    occupied[100:105, 95:105, 0:3] = 4
    ctx = no_warnings()
    try:
        if metric_kind == "miou":
            m = MIoU()
            m.add(free, free)
            assert math.isnan(m.result()["mIoU"]) and math.isnan(m.result()["IoU_geometry"])
            m.add(free, occupied)                   # GT occupied, prediction all free
            r = m.result()
            assert r["per_class"][4] == 0 and r["mIoU"] == 0 and r["IoU_geometry"] == 0
        else:
            m = RayIoU(directions=np.array(AXES + DIAGONALS[:6]))
            m.add(free, free, np.zeros((1, 3)))
            r = m.result()
            assert m.rays == 0 and math.isnan(r["RayIoU"])   # every GT ray is free: dropped
            m.add(free, occupied, np.array([[0.0, 0.0, 0.0]]))
            r = m.result()
            assert m.rays > 0 and r["RayIoU"] == 0
    finally:
        ctx.__exit__(None, None, None)


@FEW
@given(corner=st.tuples(st.integers(-3, 3), st.integers(-3, 3), st.integers(0, 8)),
       shift=st.sampled_from([0, 1]))
def test_rayiou_from_origins_on_voxel_corners_in_metres(corner, shift):
    """Origins on voxel corners given in metres (x = -40 + 0.4 i): metres -> voxel units is
    rounded (to float32 as SparseOcc does), and the rays must count as SparseOcc's do."""
    rng = np.random.default_rng(sum(corner) + 10 + 100 * shift)
    gt = np.full((200, 200, 16), 17, dtype=np.uint8)
    gt[95:106, 95:106, 0] = 11
    gt[101:104, 97:103, 1:4] = 4
    gt[94:97, 99:101, 1:5] = rng.integers(0, 17)
    pred = np.roll(gt, shift, axis=0)
    origin = np.array([[-40.0 + 0.4 * (100 + corner[0]), -40.0 + 0.4 * (100 + corner[1]),
                        -1.0 + 0.4 * corner[2]]])
    dirs = np.array(AXES + DIAGONALS)
    metric = RayIoU(directions=dirs)
    metric.add(pred, gt, origin)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")                 # nanmean of all-NaN rows
        iou, ref = sparseocc_rayiou([pred], [gt], [origin], rays=dirs.astype(np.float32))
    np.testing.assert_array_equal(metric.per_class_iou(), iou)
    result = metric.result()
    assert result["RayIoU"] == ref["RayIoU"] or (math.isnan(ref["RayIoU"]) and
                                                 math.isnan(result["RayIoU"]))
