"""Ray casting and RayIoU (odg_ros/metrics/raycast.py, rayiou.py).

The fast vectorised traversal is checked against two slow float64 references written here:
an exact one (all voxel-plane crossings of the ray, sorted; the voxel of each segment from its
midpoint) and a marcher that samples the ray in tiny steps. Hand-computed cases cover single
voxels, walls at each depth threshold, axis-parallel rays, origins on faces and corners."""
import math
from fractions import Fraction

import numpy as np
import pytest

from odg_ros.metrics.raycast import cast_rays, lidar_ray_directions
from odg_ros.metrics.rayiou import LidarOrigins, RayIoU, lidar_origins

FREE = 17
SHAPE = (200, 200, 16)
GRID_MIN = np.array([-40.0, -40.0, -1.0])


# ---------------------------------------------------------------- slow float64 references

def exact_reference(occupied, o, d):
    """First occupied voxel of the ray o + t d (voxel units): (voxel or None, depth)."""
    size = np.array(occupied.shape, dtype=np.float64)
    t0, t1 = 0.0, math.inf
    for a in range(3):
        if d[a] == 0:
            if not 0 <= o[a] < size[a]:
                return None, 0.0
        else:
            ta, tb = (0 - o[a]) / d[a], (size[a] - o[a]) / d[a]
            t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    if not t0 < t1:
        return None, 0.0
    ts = [t0, t1]
    for a in range(3):
        if d[a] != 0:
            t = (np.arange(int(size[a]) + 1) - o[a]) / d[a]
            ts.extend(t[(t > t0) & (t < t1)])
    ts = np.unique(ts)
    for start, end in zip(ts[:-1], ts[1:]):
        if end - start <= 1e-9:  # zero-length chord: the ray only touches this voxel
            continue
        v = exact_floor(o, 0.5 * (start + end), d)
        if occupied[v]:
            return v, end
    return None, t1


def exact_floor(o, t, d):
    """floor(o + t d) per axis; exact rational arithmetic where float rounding could decide
    (e.g. a direction component of 1e-16 moving an origin off a voxel face)."""
    p = o + t * d
    v = np.floor(p).astype(int)
    for a in np.flatnonzero(np.abs(p - np.round(p)) < 1e-6):
        v[a] = math.floor(Fraction(o[a]) + Fraction(t) * Fraction(d[a]))
    return tuple(v)


def tiny_step_reference(occupied, o, d, h):
    """Sample the ray every h: (first occupied voxel sampled or None, its exit distance or the
    last sampled distance inside the grid)."""
    size = np.array(occupied.shape)
    t_far = np.linalg.norm(size) + np.linalg.norm(o - size / 2) + 1
    t = np.arange(h / 2, t_far, h)
    v = np.floor(o + t[:, None] * d).astype(int)
    inside = np.all((v >= 0) & (v < size), axis=1)
    occ = np.zeros(len(t), dtype=bool)
    occ[inside] = occupied[v[inside, 0], v[inside, 1], v[inside, 2]]
    if not occ.any():
        return None, (t[inside][-1] if inside.any() else 0.0)
    voxel = v[np.argmax(occ)]
    exits = [((voxel[a] + (d[a] > 0)) - o[a]) / d[a] for a in range(3) if d[a] != 0]
    return tuple(voxel), min(exits)


def voxel_entry(voxel, o, d):
    entries = [((voxel[a] + (d[a] < 0)) - o[a]) / d[a] for a in range(3) if d[a] != 0]
    return max(0.0, max(entries))


def unravel(index, shape):
    return None if index < 0 else tuple(int(i) for i in np.unravel_index(index, shape))


def random_unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def special_directions():
    dirs = [np.eye(3)[a] * s for a in range(3) for s in (1, -1)]
    for sx in (1, -1):
        for sy in (1, -1):
            dirs += [np.array([sx, sy, 0.0]) / math.sqrt(2),
                     np.array([sx, 0.0, sy]) / math.sqrt(2),
                     np.array([sx, sy, 1.0]) / math.sqrt(3),
                     np.array([sx, sy, -1.0]) / math.sqrt(3),
                     np.array([0.6 * sx, 0.8 * sy, 0.0])]
    return np.array(dirs)


def mixed_origins(rng, shape, n):
    """Origins inside, on voxel corners, on faces and outside the grid."""
    size = np.array(shape, dtype=np.float64)
    inside = rng.random((n, 3)) * size
    corners = rng.integers(0, size + 1, (n, 3)).astype(np.float64)
    corners[:2] = [[0, 0, 0], size]  # the grid's own corners
    faces = rng.random((n, 3)) * size
    faces[np.arange(n), rng.integers(0, 3, n)] = rng.integers(0, 4, n)
    outside = rng.random((n, 3)) * size
    outside[:, 2] = np.where(rng.random(n) < 0.5, -2.5, size[2] + 3.0)
    return np.concatenate([inside, corners, faces, outside])



# ---------------------------------------------------------------- the LiDAR pattern

def test_lidar_ray_pattern():
    dirs = lidar_ray_directions()
    assert dirs.shape == (39 * 360, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
    pitch = np.arcsin(dirs[::360, 2])
    assert pitch[0] == pytest.approx(-math.pi / 4)
    assert pitch[9] == pytest.approx(-(math.pi / 2 - math.atan(10)))
    np.testing.assert_allclose(np.diff(pitch[9:]), math.atan(10) - math.atan(9), atol=1e-12)
    assert pitch[-2] < 0.21 < pitch[-1]
    azimuth = np.degrees(np.arctan2(dirs[:360, 1], dirs[:360, 0])) % 360
    np.testing.assert_allclose(azimuth, np.arange(360), atol=1e-9)


# ---------------------------------------------------------------- hand-computed traversals

def cast_one(occupied, origin, direction):
    index, depth = cast_rays(occupied.astype(np.uint8), np.array([origin], dtype=float),
                             np.array([direction], dtype=float))
    return unravel(index[0, 0], occupied.shape), depth[0, 0]


def test_single_voxel():
    occ = np.zeros((20, 20, 8), dtype=bool)
    occ[12, 5, 3] = True
    # along +x from the centre of voxel (5, 5, 3): enters at x = 12, leaves at x = 13
    assert cast_one(occ, (5.5, 5.5, 3.5), (1, 0, 0)) == ((12, 5, 3), pytest.approx(7.5))
    # the opposite way nothing is hit: the ray leaves the grid at x = 0
    assert cast_one(occ, (5.5, 5.5, 3.5), (-1, 0, 0)) == (None, pytest.approx(5.5))
    # a ray passing one voxel beside it misses it
    assert cast_one(occ, (5.5, 6.5, 3.5), (1, 0, 0)) == (None, pytest.approx(14.5))
    # origin inside the occupied voxel: hit at once, depth to its exit
    assert cast_one(occ, (12.25, 5.5, 3.5), (1, 0, 0)) == ((12, 5, 3), pytest.approx(0.75))


def test_axis_parallel_rays_in_every_direction():
    occ = np.zeros((20, 20, 8), dtype=bool)
    occ[15, 10, 4] = occ[2, 10, 4] = occ[10, 18, 4] = occ[10, 1, 4] = occ[10, 10, 7] = True
    occ[10, 10, 0] = True
    o = (10.5, 10.5, 4.5)
    assert cast_one(occ, o, (1, 0, 0)) == ((15, 10, 4), pytest.approx(5.5))
    assert cast_one(occ, o, (-1, 0, 0)) == ((2, 10, 4), pytest.approx(8.5))
    assert cast_one(occ, o, (0, 1, 0)) == ((10, 18, 4), pytest.approx(8.5))
    assert cast_one(occ, o, (0, -1, 0)) == ((10, 1, 4), pytest.approx(9.5))
    assert cast_one(occ, o, (0, 0, 1)) == ((10, 10, 7), pytest.approx(3.5))
    assert cast_one(occ, o, (0, 0, -1)) == ((10, 10, 0), pytest.approx(4.5))


def test_origin_on_a_voxel_face():
    occ = np.zeros((20, 20, 8), dtype=bool)
    occ[9, 5, 3] = True
    # on the face x = 10 between voxels 9 and 10: moving -x the ray starts in voxel 9
    assert cast_one(occ, (10.0, 5.5, 3.5), (-1, 0, 0)) == ((9, 5, 3), pytest.approx(1.0))
    # moving +x it starts in voxel 10 and never enters voxel 9
    assert cast_one(occ, (10.0, 5.5, 3.5), (1, 0, 0)) == (None, pytest.approx(10.0))
    # a ray lying in the face z = 3 belongs to the voxels above it (floor)
    occ2 = np.zeros((20, 20, 8), dtype=bool)
    occ2[14, 5, 2] = True   # below the face: not hit
    occ2[16, 5, 3] = True   # above the face: hit
    assert cast_one(occ2, (10.5, 5.5, 3.0), (1, 0, 0)) == ((16, 5, 3), pytest.approx(6.5))


def test_origin_on_a_voxel_corner_and_diagonal_rays():
    occ = np.zeros((20, 20, 8), dtype=bool)
    occ[11, 10, 4] = True   # touched only along an edge by the diagonal: not hit
    occ[10, 11, 4] = True   # likewise
    occ[13, 13, 4] = True
    d = (1 / math.sqrt(2), 1 / math.sqrt(2), 0.0)
    assert cast_one(occ, (10.0, 10.0, 4.5), d) == ((13, 13, 4), pytest.approx(4 * math.sqrt(2)))
    # from the corner (10, 10, 4) along (-1, -1, -1): voxels (9, 9, 3), (8, 8, 2), ...
    occ3 = np.zeros((20, 20, 8), dtype=bool)
    occ3[9, 9, 4] = occ3[9, 10, 3] = True   # share only an edge / corner with the path
    occ3[7, 7, 1] = True
    d3 = (-1 / math.sqrt(3),) * 3
    assert cast_one(occ3, (10.0, 10.0, 4.0), d3) == ((7, 7, 1), pytest.approx(3 * math.sqrt(3)))


def test_origin_outside_the_grid():
    occ = np.zeros((20, 20, 8), dtype=bool)
    occ[5, 5, 7] = True
    # from above the grid straight down: enters at z = 8, hit voxel left at z = 7
    assert cast_one(occ, (5.5, 5.5, 10.0), (0, 0, -1)) == ((5, 5, 7), pytest.approx(3.0))
    # pointing away from the grid: never enters
    assert cast_one(occ, (5.5, 5.5, 10.0), (0, 0, 1)) == (None, 0.0)


def test_layers_are_traversed_together_but_hit_separately():
    bits = np.zeros((20, 20, 8), dtype=np.uint8)
    bits[8, 5, 3] |= 1
    bits[12, 5, 3] |= 2
    bits[15, 5, 3] |= 3
    index, depth = cast_rays(bits, [[5.5, 5.5, 3.5]], [[1.0, 0, 0]], num_bits=2)
    assert unravel(index[0, 0], bits.shape) == (8, 5, 3) and depth[0, 0] == pytest.approx(3.5)
    assert unravel(index[1, 0], bits.shape) == (12, 5, 3) and depth[1, 0] == pytest.approx(7.5)


def test_bad_rays_are_a_clear_error():
    occ = np.zeros((4, 4, 4), dtype=np.uint8)
    with pytest.raises(ValueError, match="unit"):
        cast_rays(occ, [[1.0, 1, 1]], [[2.0, 0, 0]])
    with pytest.raises(ValueError, match="finite"):
        cast_rays(occ, [[np.nan, 1, 1]], [[1.0, 0, 0]])
    with pytest.raises(ValueError, match="differ"):
        cast_rays(occ, [[1.0, 1, 1]], [[1.0, 0, 0], [0, 1.0, 0]])


# ---------------------------------------------------------------- against the references

def run_against_references(occupied, origins, directions, marcher_rays, h, rng):
    O = np.repeat(origins, len(directions), axis=0)
    D = np.tile(directions, (len(origins), 1))
    index, depth = cast_rays(occupied.astype(np.uint8), O, D)
    hits = 0
    for r in range(len(O)):
        voxel, ref_depth = exact_reference(occupied, O[r], D[r])
        assert unravel(index[0, r], occupied.shape) == voxel, (O[r], D[r])
        assert depth[0, r] == pytest.approx(ref_depth, abs=1e-9), (O[r], D[r])
        hits += voxel is not None
    assert 0.1 * len(O) < hits < len(O)  # the case mix exercises hits and misses
    # the tiny-step marcher can only miss voxels whose chord along the ray is below ~h
    skipped = 0
    for r in rng.choice(len(O), size=min(marcher_rays, len(O)), replace=False):
        voxel, ref_depth = tiny_step_reference(occupied, O[r], D[r], h)
        fast = unravel(index[0, r], occupied.shape)
        if fast == voxel:
            tol = 1e-9 if voxel is not None else h
            assert depth[0, r] == pytest.approx(ref_depth, abs=tol), (O[r], D[r])
        else:
            assert fast is not None, (O[r], D[r])
            assert depth[0, r] - voxel_entry(fast, O[r], D[r]) < 2 * h, (O[r], D[r])
            skipped += 1
    assert skipped <= 0.01 * marcher_rays


def test_random_small_grids_match_references():
    rng = np.random.default_rng(7)
    for shape, density in (((12, 10, 8), 0.04), ((9, 13, 5), 0.12)):
        occupied = rng.random(shape) < density
        origins = mixed_origins(rng, shape, 6)
        directions = np.concatenate([random_unit(rng, 40), special_directions(),
                                     lidar_ray_directions()[::293]])
        run_against_references(occupied, origins, directions, 1500, 2e-3, rng)


def test_full_grid_lidar_pattern_matches_exact_reference():
    rng = np.random.default_rng(3)
    occupied = np.zeros(SHAPE, dtype=bool)
    occupied[:, :, :3] = True                          # ground
    occupied |= rng.random(SHAPE) < 0.002              # clutter
    occupied[150:170, 40:60, 3:10] = True              # a building
    origins = (np.array([[0.94, 0.0, 1.84], [-12.3, 4.1, 1.9], [20.0, -8.0, 2.0]])
               - GRID_MIN) / 0.4
    origins[2] = np.round(origins[2])                  # one origin on a voxel corner
    directions = lidar_ray_directions()[::17]
    run_against_references(occupied, origins, directions, 60, 1e-2, rng)


# ---------------------------------------------------------------- RayIoU counting

AXIS_DIRS = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]])


def voxel_centre(i, j, k):
    return GRID_MIN + (np.array([i, j, k]) + 0.5) * 0.4


@pytest.mark.parametrize("shift, expected_tp", [
    (2, (1, 1, 1)),   # pred wall 0.8 m behind the GT wall: a hit at every threshold
    (3, (0, 1, 1)),   # 1.2 m
    (4, (0, 1, 1)),   # 1.6 m
    (6, (0, 0, 1)),   # 2.4 m
    (9, (0, 0, 1)),   # 3.6 m
    (11, (0, 0, 0)),  # 4.4 m
    (-2, (1, 1, 1)),  # in front of the GT wall
    (-3, (0, 1, 1)),
    (-11, (0, 0, 0)),
])
def test_wall_depth_thresholds(shift, expected_tp):
    gt = np.full(SHAPE, FREE, dtype=np.uint8)
    pred = gt.copy()
    gt[140, :, :] = 15
    pred[140 + shift, :, :] = 15
    metric = RayIoU(directions=AXIS_DIRS[:1])
    metric.add(pred, gt, voxel_centre(100, 100, 7)[None])
    # one ray, GT manmade at 40 x 0.4 = 16.2 m (voxel exit 141 * 0.4 - 40 - 0.2)
    (label, d_pred), (_, d_gt) = metric.cast(pred, voxel_centre(100, 100, 7)[None], gt)
    assert d_gt[0] == pytest.approx(16.2)
    assert d_pred[0] - d_gt[0] == pytest.approx(0.4 * shift)
    res = metric.result()
    for t, tp in zip((1, 2, 4), expected_tp):
        assert res[f"RayIoU@{t}"] == tp               # IoU of manmade is 1 or 0; others NaN
    assert res["RayIoU"] == pytest.approx(np.mean(expected_tp))
    assert np.isnan(np.delete(res["per_class"], 15)).all()


def room(shift_y=0):
    """Manmade walls 10 voxels from voxel (100, 100, *) on all four sides, and a car 5 voxels
    ahead (+x); the whole scene optionally shifted along y."""
    g = np.full(SHAPE, FREE, dtype=np.uint8)
    y = slice(85 + shift_y, 116 + shift_y)
    g[110, y, :] = 15
    g[90, y, :] = 15
    g[85:116, 110 + shift_y, :] = 15
    g[85:116, 90 + shift_y, :] = 15
    g[105, 100 + shift_y, 7] = 4
    return g


def test_scene_shifted_by_one_voxel_hand_computed():
    # Pred = GT shifted one voxel along +y. Four axis rays from voxel (100, 100, 7):
    # +x: GT car at 5 voxels, pred misses the car and hits the wall (manmade)  -> car FN/ manmade FP
    # -x: same wall depth in both                                               -> manmade TP
    # +y: pred wall 0.4 m farther, -y: pred wall 0.4 m closer                   -> manmade TP
    # car IoU = 0 / 1 = 0; manmade IoU = 3 / (3 + 4 - 3) = 0.75 at every threshold.
    metric = RayIoU(directions=AXIS_DIRS)
    metric.add(room(shift_y=1), room(), voxel_centre(100, 100, 7)[None])
    res = metric.result()
    assert res["per_class"][4] == 0.0 and res["per_class"][15] == pytest.approx(0.75)
    for t in (1, 2, 4):
        assert res[f"RayIoU@{t}"] == pytest.approx(0.375)
    assert res["RayIoU"] == pytest.approx(0.375)
    assert res["rays"] == 4 and res["samples"] == 1


def driving_scene(rng):
    g = np.full(SHAPE, FREE, dtype=np.uint8)
    g[:, :, :3] = 11
    g[:, 130:, :3] = 13
    for _ in range(25):
        x, y = rng.integers(20, 180, 2)
        g[x:x + 11, y:y + 5, 3:7] = rng.choice([4, 10, 3])
    g[:, 175:, 3:14] = 15
    g[:, :15, 3:12] = 16
    return g


def reference_rayiou(pred, gt, origins, directions, num_classes=17):
    """Counting written out ray by ray with the exact reference traversal."""
    gt_n, pred_n = np.zeros(num_classes), np.zeros(num_classes)
    tp = np.zeros((3, num_classes))
    for o in (origins - GRID_MIN) / 0.4:
        for d in directions:
            gv, gd = exact_reference(gt != FREE, o, d)
            if gv is None:
                continue
            pv, pd = exact_reference(pred != FREE, o, d)
            g_label = gt[gv]
            p_label = pred[pv] if pv is not None else FREE
            gt_n[g_label] += 1
            if p_label != FREE:
                pred_n[p_label] += 1
            for j, t in enumerate((1, 2, 4)):
                if p_label == g_label and abs(pd - gd) * 0.4 < t:
                    tp[j, g_label] += 1
    union = gt_n + pred_n - tp
    iou = np.where(union > 0, tp / np.maximum(union, 1), np.nan)
    return iou, np.mean([np.nanmean(row) for row in iou])


def test_shifted_prediction_matches_reference_counting():
    rng = np.random.default_rng(11)
    gt = driving_scene(rng)
    pred = np.full_like(gt, FREE)
    pred[1:] = gt[:-1]                                  # shifted one voxel along +x
    pred[rng.random(SHAPE) < 0.01] = 4                  # and some spurious cars
    origins = np.array([[0.94, 0.0, 1.84], [-20.3, 1.5, 1.8]])
    directions = lidar_ray_directions()[::23]
    metric = RayIoU(directions=directions)
    metric.add(pred, gt, origins)
    iou, rayiou = reference_rayiou(pred, gt, origins, directions)
    res = metric.result()
    np.testing.assert_allclose(res["per_class_at"], iou, equal_nan=True, atol=1e-12)
    assert res["RayIoU"] == pytest.approx(rayiou, abs=1e-12)
    assert 0.2 < res["RayIoU"] < 0.95                   # a real, partial drop


def test_perfect_and_all_free_predictions():
    rng = np.random.default_rng(5)
    gt = driving_scene(rng)
    origins = np.array([[0.94, 0.0, 1.84], [10.0, 3.0, 1.84]])
    perfect = RayIoU()
    perfect.add(gt.copy(), gt, origins)
    res = perfect.result()
    assert res["RayIoU"] == 1.0 and all(res[f"RayIoU@{t}"] == 1.0 for t in (1, 2, 4))
    present = ~np.isnan(res["per_class"])
    assert set(np.flatnonzero(present)) <= {3, 4, 10, 11, 13, 15, 16}
    assert np.isnan(res["per_class"][[0, 1, 2, 5]]).all()   # absent classes: NaN, excluded
    empty = RayIoU()
    empty.add(np.full_like(gt, FREE), gt, origins)
    res0 = empty.result()
    assert res0["RayIoU"] == 0.0
    np.testing.assert_array_equal(np.isnan(res0["per_class"]), ~present)


def test_class_predicted_but_absent_from_gt_counts_as_zero():
    # RayIoU (SparseOcc): NaN only when a class is in neither GT nor prediction.
    metric = RayIoU(directions=AXIS_DIRS[:2])
    metric.add_rays(np.array([4, 10]), np.array([5.0, 5.0]),
                    np.array([4, 4]), np.array([5.0, 5.0]))
    iou = metric.result()["per_class"]
    assert iou[4] == pytest.approx(0.5) and iou[10] == 0.0 and np.isnan(iou[3])
    assert metric.result()["RayIoU"] == pytest.approx(0.25)


def test_gt_free_rays_are_dropped_and_split_is_accumulated():
    metric = RayIoU()
    metric.add_rays(np.array([4, 4]), np.array([3.0, 9.0]), np.array([4, FREE]),
                    np.array([3.5, 40.0]))
    metric.add_rays(np.array([FREE]), np.array([40.0]), np.array([4]), np.array([3.0]))
    # car: gt 2, pred 1 (the pred car on a GT-free ray is dropped), TP 1 -> 1 / 2
    assert metric.result()["per_class"][4] == pytest.approx(0.5)
    assert metric.rays == 2


def test_waymo_label_set_and_bad_input():
    metric = RayIoU(num_classes=15, directions=AXIS_DIRS)
    g = np.full(SHAPE, 15, dtype=np.uint8)
    g[110, 95:106, :] = 10
    metric.add(g, g, voxel_centre(100, 100, 7)[None])
    assert metric.result()["per_class"].shape == (15,)
    assert metric.result()["RayIoU"] == 1.0
    with pytest.raises(ValueError, match="outside 0..15"):
        metric.add(np.full(SHAPE, 17, dtype=np.uint8), g, voxel_centre(100, 100, 7)[None])
    with pytest.raises(ValueError, match="origins"):
        metric.add(g, g, np.zeros((3,)))


def test_no_origins_adds_no_rays():
    metric = RayIoU()
    g = np.full(SHAPE, FREE, dtype=np.uint8)
    metric.add(g, g, np.zeros((0, 3)))
    assert metric.samples == 1 and metric.rays == 0 and np.isnan(metric.result()["RayIoU"])


# ---------------------------------------------------------------- LiDAR origins from infos

def pose(yaw, x, y, z=0.0):
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:3, 3] = [x, y, z]
    return T


def make_scene(token, n, step, start_time, lidar2ego):
    return [{"token": f"{token}-{k}", "scene_token": token, "timestamp": start_time + k * 500000,
             "ego_pose": pose(0.05 * k, 100 + step * k, 50 + 0.3 * k * k, 0.1 * k),
             "lidar2ego": lidar2ego} for k in range(n)]


def expected_origins(frames, ref):
    out = []
    for f in frames:
        p = np.linalg.inv(ref["ego_pose"]) @ f["ego_pose"] @ f["lidar2ego"] @ [0, 0, 0, 1]
        if abs(p[0]) < 39 and abs(p[1]) < 39:
            out.append(p[:3])
    if len(out) > 8:
        out = [out[i] for i in np.round(np.linspace(0, len(out) - 1, 8)).astype(int)]
    return np.array(out)


def test_lidar_origins_from_infos():
    lidar2ego = pose(-math.pi / 2, 0.94, 0.0, 1.84)
    a = make_scene("A", 20, 2.5, 0, lidar2ego)       # 20 keyframes, 47.5 m: some filtered
    b = make_scene("B", 5, 1.0, 10**9, lidar2ego)
    infos = [b[3], a[5], b[0]] + a[:5] + a[6:] + b[1:3] + b[4:]   # order must not matter
    origins = LidarOrigins(infos)
    for frames in (a, b):
        for ref in frames:
            got = origins(infos.index(ref))
            np.testing.assert_allclose(got, expected_origins(frames, ref), atol=1e-9)
    # scene B: nothing filtered, so origin k is keyframe k's LiDAR; its own is lidar2ego's
    for k, ref in enumerate(b):
        np.testing.assert_allclose(origins(infos.index(ref))[k], [0.94, 0.0, 1.84], atol=1e-12)
    assert len(origins(infos.index(a[10]))) == 8         # 16 within 39 m -> 8 picked
    assert len(origins(infos.index(b[2]))) == 5
    np.testing.assert_allclose(lidar_origins(infos, 0), origins(0))


def test_lidar_origins_bad_pose_is_a_clear_error():
    frames = make_scene("A", 2, 1.0, 0, np.eye(4))
    frames[1]["ego_pose"] = np.eye(3)
    with pytest.raises(ValueError, match="A-1: ego_pose"):
        LidarOrigins(frames)
