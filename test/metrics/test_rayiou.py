"""Ray casting and RayIoU (odg_ros/metrics/raycast.py, rayiou.py) against SparseOcc's.

The oracle is testing/sparseocc_reference.py, a scalar line-by-line transcription of SparseOcc's
``lib/dvr/dvr.cu`` (test phase), ``loaders/ray_metrics.py`` and ``loaders/ego_pose_dataset.py``:
the vectorised caster must report the same voxel and the same distance, bit for bit, for every
ray. Hand-computed cases pin down what SparseOcc does at faces, edges, ties and the grid border.
"""
import math

import numpy as np
import pytest
from testing.helpers import driving_scene

from odg_ros.metrics.raycast import (MAX_STEP, cast_rays, lidar_ray_directions,
                                     rays_in_voxel_units)
from odg_ros.metrics.rayiou import LidarOrigins, RayIoU, lidar_origins

from testing.sparseocc_reference import (lidar_rays, process_one_sample, render_forward_one_ray,
                                 sparseocc_origins, sparseocc_rayiou)
from testing.metrics import rays_from, unravel

FREE = 17
SHAPE = (200, 200, 16)
GRID_MIN = np.array([-40.0, -40.0, -1.0])


def random_unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def lattice_directions():
    """Axis-parallel, face- and body-diagonal rays, and rays tilted 1e-7 off an axis."""
    dirs = [np.eye(3)[a] * s for a in range(3) for s in (1, -1)]
    for sx in (-1, 0, 1):
        for sy in (-1, 0, 1):
            for sz in (-1, 0, 1):
                if abs(sx) + abs(sy) + abs(sz) >= 2:
                    dirs.append(np.array([sx, sy, sz]) / math.sqrt(abs(sx) + abs(sy) + abs(sz)))
    for a in range(3):
        for tilt in (1e-7, -1e-7):
            d = np.eye(3)[a].copy()
            d[(a + 1) % 3] = tilt
            dirs.append(d / np.linalg.norm(d))
    return np.array(dirs)


def special_origins(rng, shape, n):
    """Origins inside, on voxel faces, edges and corners (the grid's own included), and
    outside the grid on every side (negative coordinates truncate towards zero)."""
    size = np.array(shape, dtype=np.float64)
    inside = rng.random((n, 3)) * size
    corners = rng.integers(0, size + 1, (n, 3)).astype(np.float64)
    corners[:2] = [[0, 0, 0], size]
    faces = rng.random((n, 3)) * size
    faces[np.arange(n), rng.integers(0, 3, n)] = rng.integers(0, 4, n)
    edges = rng.integers(0, size + 1, (n, 3)).astype(np.float64)
    edges[np.arange(n), rng.integers(0, 3, n)] += rng.random(n)
    outside = rng.random((n, 3)) * (size + 6) - 3
    return np.concatenate([inside, corners, faces, edges, outside])


def assert_same_as_sparseocc(occupied, starts, ends):
    """cast_rays against the scalar transcription, ray by ray: voxel and distance exactly."""
    voxel, depth = cast_rays(occupied.astype(np.uint8), starts, ends)
    grid = occupied.tolist()
    for r in range(len(starts)):
        ref_depth, ref_voxel = render_forward_one_ray(grid, starts[r], ends[r])
        assert unravel(voxel[0, r], occupied.shape) == ref_voxel, (starts[r], ends[r])
        # the same double, sign of zero included
        assert depth[0, r].tobytes() == np.float64(ref_depth).tobytes(), (starts[r], ends[r])
    return voxel, depth


# ---------------------------------------------------------------- the LiDAR pattern

def test_lidar_ray_pattern():
    dirs = lidar_ray_directions()
    assert dirs.dtype == np.float32 and dirs.shape == (39 * 360, 3)
    np.testing.assert_array_equal(dirs, lidar_rays())
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-6)
    pitch = np.arcsin(dirs[::360, 2].astype(np.float64))
    assert pitch[0] == pytest.approx(-math.pi / 4)
    assert pitch[-2] < 0.21 < pitch[-1]


# ---------------------------------------------------------------- hand-computed traversals

def cast_one(occupied, origin, direction):
    start, end = rays_from([origin], [direction])
    voxel, depth = cast_rays(occupied.astype(np.uint8), start, end)
    return unravel(voxel[0, 0], occupied.shape), depth[0, 0]


def test_single_voxel_and_no_hit():
    occ = np.zeros((20, 20, 8), dtype=bool)
    occ[12, 5, 3] = True
    assert cast_one(occ, (5.5, 5.5, 3.5), (1, 0, 0)) == ((12, 5, 3), 7.5)
    # no hit: the last voxel inside (free) and where the ray leaves the grid
    assert cast_one(occ, (5.5, 5.5, 3.5), (-1, 0, 0)) == ((0, 5, 3), 5.5)
    assert cast_one(occ, (12.25, 5.5, 3.5), (1, 0, 0)) == ((12, 5, 3), 0.75)


def test_origin_on_a_face_starts_in_the_voxel_on_the_plus_side():
    occ = np.zeros((20, 20, 8), dtype=bool)
    occ[10, 5, 3] = occ[9, 5, 3] = True
    # int(10.0) = 10: moving -x, voxel 10 is visited first, with exit distance -0.0
    voxel, depth = cast_one(occ, (10.0, 5.5, 3.5), (-1, 0, 0))
    assert voxel == (10, 5, 3) and depth == 0.0 and math.copysign(1, depth) == -1
    occ[10, 5, 3] = False
    assert cast_one(occ, (10.0, 5.5, 3.5), (-1, 0, 0)) == ((9, 5, 3), 1.0)
    # a ray lying in the face z = 3 walks the row above it
    occ2 = np.zeros((20, 20, 8), dtype=bool)
    occ2[14, 5, 2] = True
    occ2[16, 5, 3] = True
    assert cast_one(occ2, (10.5, 5.5, 3.0), (1, 0, 0)) == ((16, 5, 3), 6.5)


def test_ties_step_one_axis_preferring_z_then_y():
    # from the corner (10, 10, 4) along (-1, -1, -1)/sqrt 3: all three planes at once; z steps
    # first, then y, then x, visiting the voxels between them with zero-length chords
    occ = np.zeros((20, 20, 8), dtype=bool)
    occ[10, 9, 3] = True          # reached after z and y stepped, before x
    d = (-1 / math.sqrt(3),) * 3
    voxel, depth = cast_one(occ, (10.0, 10.0, 4.0), d)
    assert voxel == (10, 9, 3) and abs(depth) < 1e-6
    # x = y tie in the plane z = const: y steps first
    occ2 = np.zeros((20, 20, 8), dtype=bool)
    occ2[10, 11, 4] = True
    voxel, _ = cast_one(occ2, (10.0, 10.0, 4.5), (1 / math.sqrt(2), 1 / math.sqrt(2), 0.0))
    assert voxel == (10, 11, 4)


def test_origin_outside_the_grid_and_rays_that_never_enter():
    occ = np.zeros((20, 20, 8), dtype=bool)
    occ[5, 5, 7] = True
    occ[0, 0, 0] = True
    assert cast_one(occ, (5.5, 5.5, 10.0), (0, 0, -1)) == ((5, 5, 7), 3.0)
    # never enters: voxel (0, 0, 0) and distance -1
    assert cast_one(occ, (5.5, 5.5, 10.0), (0, 0, 1)) == ((0, 0, 0), -1.0)
    assert cast_one(occ, (-3.5, 5.5, 3.5), (0, 1, 0)) == ((0, 0, 0), -1.0)
    # int(-0.5) = 0: an origin half a voxel below the grid starts "inside" voxel z = 0
    occ[5, 5, 0] = True
    assert cast_one(occ, (5.5, 5.5, -0.5), (0, 0, 1)) == ((5, 5, 0), 1.5)


def test_step_limit():
    occ = np.zeros((1100, 1, 1), dtype=bool)
    occ[1050, 0, 0] = True
    # MAX_STEP + 1 voxels are visited, the hit beyond them is never reached
    assert cast_one(occ, (0.5, 0.5, 0.5), (1, 0, 0)) == ((MAX_STEP, 0, 0), MAX_STEP + 0.5)
    # from outside, the steps before entering count too
    # (int(-60.5) = -60: voxels -60 .. 940, the last one left at 941 + 60.5)
    assert cast_one(occ, (-60.5, 0.5, 0.5), (1, 0, 0)) == ((MAX_STEP - 60, 0, 0), 1001.5)
    assert_same_as_sparseocc(occ, *rays_from([[0.5, 0.5, 0.5], [-60.5, 0.5, 0.5]], [[1, 0, 0]]))


def test_layers_are_traversed_together_but_hit_separately():
    bits = np.zeros((20, 20, 8), dtype=np.uint8)
    bits[8, 5, 3] |= 1
    bits[12, 5, 3] |= 2
    bits[15, 5, 3] |= 3
    start, end = rays_from([[5.5, 5.5, 3.5]], [[1.0, 0, 0]])
    voxel, depth = cast_rays(bits, start, end, num_bits=2)
    assert unravel(voxel[0, 0], bits.shape) == (8, 5, 3) and depth[0, 0] == 3.5
    assert unravel(voxel[1, 0], bits.shape) == (12, 5, 3) and depth[1, 0] == 7.5


def test_bad_rays_are_a_clear_error():
    occ = np.zeros((4, 4, 4), dtype=np.uint8)
    with pytest.raises(ValueError, match="no direction"):
        cast_rays(occ, [[1.0, 1, 1]], [[1.0, 1, 1]])
    with pytest.raises(ValueError, match="finite"):
        cast_rays(occ, [[np.nan, 1, 1]], [[1.0, 0, 0]])
    with pytest.raises(ValueError, match="differ"):
        cast_rays(occ, [[1.0, 1, 1]], [[1.0, 0, 0], [0, 1.0, 0]])


# ---------------------------------------------------------------- ray by ray against SparseOcc

@pytest.mark.parametrize("shape, density", [((12, 10, 8), 0.04), ((9, 13, 5), 0.15),
                                            ((6, 7, 4), 0.0), ((5, 5, 3), 1.0)])
def test_random_grids_match_sparseocc_ray_by_ray(shape, density):
    rng = np.random.default_rng(sum(shape) + int(100 * density))
    occupied = rng.random(shape) < density
    directions = np.concatenate([random_unit(rng, 12), lattice_directions()])
    start, end = rays_from(special_origins(rng, shape, 3), directions)
    voxel, depth = assert_same_as_sparseocc(occupied, start, end)
    if 0 < density < 1:   # the mix exercises hits, misses and rays that never enter
        assert (depth == -1).any() and (depth > 0).any()


def test_synthetic_world_from_the_ego_origin_matches_sparseocc():
    # The LiDAR at ego y = 0 lies on the plane between voxel rows 99 and 100; rays at azimuth
    # 0 and 180 degrees lie in that plane, those with a -y component start in row 100.
    rng = np.random.default_rng(3)
    occupied = np.zeros(SHAPE, dtype=bool)
    occupied[:, :, :3] = True
    occupied |= rng.random(SHAPE) < 0.002
    occupied[150:170, 40:60, 3:10] = True
    occupied[:, 99:101, 3] = True       # both rows next to the origins' plane
    occupied[150, 100, 7] = True        # the third origin's own voxel
    origins = np.array([[0.985793, 0.0, 1.84019], [-12.3, 4.1, 1.9], [20.0, 0.0, 2.0]])
    directions = lidar_ray_directions()
    pick = np.concatenate([np.arange(0, len(directions), 11), np.arange(270, 14040, 360),
                           np.arange(0, 14040, 180)])   # azimuths 270, 0 and 180 at every pitch
    o = np.repeat(origins, len(pick), axis=0)
    start, end = rays_in_voxel_units(o, np.tile(directions[pick], (len(origins), 1)),
                                     GRID_MIN, 0.4)
    assert start[0, 1] == np.float32(100.0)           # float32 rounds y onto the plane
    voxel, depth = assert_same_as_sparseocc(occupied, start, end)
    # the third origin lies on an x face and a y face: every ray that moves -x or -y (from
    # the float32 end points) hits the origin's voxel at -0.0, the others where they leave it
    third = depth[0, 2 * len(pick):]
    leaving = (end[2 * len(pick):, :2] < start[2 * len(pick):, :2]).any(axis=1)
    assert (third[leaving] == 0).all() and (np.signbit(third[leaving])).all()
    assert (third[~leaving] > 0).all()


# ---------------------------------------------------------------- RayIoU against SparseOcc

def test_rayiou_equals_the_transcription_on_a_perturbed_prediction():
    rng = np.random.default_rng(11)
    gt = driving_scene(rng)
    pred = np.full_like(gt, FREE)
    pred[1:] = gt[:-1]                                  # shifted one voxel along +x
    relabel = rng.random(SHAPE) < 0.03
    pred[relabel] = rng.integers(0, FREE + 1, relabel.sum())
    origins = np.array([[0.985793, 0.0, 1.84019], [-20.3, 1.5, 1.8]])
    directions = lidar_ray_directions()[::29]
    metric = RayIoU(directions=directions)
    metric.add(pred, gt, origins)
    # per ray: labels and float32 depths as SparseOcc's process_one_sample writes them
    (p_label, p_depth), (g_label, g_depth) = metric.cast(pred, origins, gt)
    ref_pred = process_one_sample(pred, directions, origins, FREE)
    ref_gt = process_one_sample(gt, directions, origins, FREE)
    np.testing.assert_array_equal(p_label, ref_pred[:, 0])
    np.testing.assert_array_equal(p_depth, ref_pred[:, 1])
    np.testing.assert_array_equal(g_label, ref_gt[:, 0])
    np.testing.assert_array_equal(g_depth, ref_gt[:, 1])
    iou, ref = sparseocc_rayiou([pred], [gt], [origins], rays=directions)
    res = metric.result()
    np.testing.assert_array_equal(res["per_class_at"], iou)
    for key in ("RayIoU", "RayIoU@1", "RayIoU@2", "RayIoU@4"):
        assert res[key] == ref[key]
    assert 0.02 < res["RayIoU"] < 0.95                  # a real, partial drop


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
            # float32 rounding in the LiDAR frame, as SparseOcc's EgoPoseDataset: equal to
            # the transcription, within 1e-5 m of the float64 positions
            k = frames.index(ref)
            np.testing.assert_array_equal(got, sparseocc_origins(
                [(f["ego_pose"], f["lidar2ego"]) for f in frames], k))
            np.testing.assert_allclose(got, expected_origins(frames, ref), atol=1e-5)
    # scene B: nothing filtered, so origin k is keyframe k's LiDAR; its own is lidar2ego's,
    # exactly (y = 0 must stay on the voxel plane)
    for k, ref in enumerate(b):
        assert origins(infos.index(ref))[k].tolist() == [0.94, 0.0, 1.84]
    assert len(origins(infos.index(a[10]))) == 8         # 16 within 39 m -> 8 picked
    assert len(origins(infos.index(b[2]))) == 5
    np.testing.assert_allclose(lidar_origins(infos, 0), origins(0))


def test_lidar_origins_bad_pose_is_a_clear_error():
    frames = make_scene("A", 2, 1.0, 0, np.eye(4))
    frames[1]["ego_pose"] = np.eye(3)
    with pytest.raises(ValueError, match="A-1: ego_pose"):
        LidarOrigins(frames)
