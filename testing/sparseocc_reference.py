"""A plain, scalar transcription of SparseOcc's RayIoU, used as the tests' oracle.

``render_forward_one_ray`` follows the test phase of ``render_forward_cuda_kernel`` in
MCG-NJU/SparseOcc ``lib/dvr/dvr.cu`` line by line: double arithmetic on float32 inputs, C
``int()`` truncation, DBL_MAX for a zero direction component, one axis per iteration with the
kernel's nested strict comparisons, accumulated tMax, the ``step > MAX_STEP`` stop, the first
voxel with occupancy > 0.5 else the last voxel visited, and (-1, voxel (0, 0, 0)) for a ray that
never entered the grid. ``sparseocc_rayiou`` follows ``loaders/ray_metrics.py``
(``process_one_sample``, ``main_rayiou``, ``calc_rayiou``) with its float32 tensors, and
``sparseocc_origins`` follows ``loaders/ego_pose_dataset.py``. Slow on purpose: no NumPy in the
ray loop, so it shares no code or vectorisation trick with ``odg_ros.metrics.raycast``.
"""
import math

import numpy as np

MAX_STEP = 1000
DBL_MAX = 1.7976931348623157e308


def c_int(x: float) -> int:
    return int(x)  # Python int() of a float truncates towards zero, as C's does


def render_forward_one_ray(sigma, origin, end):
    """sigma: occupancy indexable as sigma[x][y][z] (the kernel's sigma[z][y][x] of the
    permuted grid), size (X, Y, Z); origin, end: three float32 values each (voxel units).
    Returns (pred_dist as double, (x, y, z) coordinate index)."""
    vxsize, vysize, vzsize = len(sigma), len(sigma[0]), len(sigma[0][0])
    xo, yo, zo = (float(c) for c in origin)
    xe, ye, ze = (float(c) for c in end)
    vx, vy, vz = c_int(xo), c_int(yo), c_int(zo)
    rx = xe - xo
    ry = ye - yo
    rz = ze - zo
    gt_d = math.sqrt(rx * rx + ry * ry + rz * rz)
    dx = rx / gt_d
    dy = ry / gt_d
    dz = rz / gt_d
    stepX = 1 if dx >= 0 else -1
    stepY = 1 if dy >= 0 else -1
    stepZ = 1 if dz >= 0 else -1
    next_voxel_boundary_x = vx + (0 if stepX < 0 else 1)
    next_voxel_boundary_y = vy + (0 if stepY < 0 else 1)
    next_voxel_boundary_z = vz + (0 if stepZ < 0 else 1)
    tMaxX = (next_voxel_boundary_x - xo) / dx if dx != 0 else DBL_MAX
    tMaxY = (next_voxel_boundary_y - yo) / dy if dy != 0 else DBL_MAX
    tMaxZ = (next_voxel_boundary_z - zo) / dz if dz != 0 else DBL_MAX
    tDeltaX = stepX / dx if dx != 0 else DBL_MAX
    tDeltaY = stepY / dy if dy != 0 else DBL_MAX
    tDeltaZ = stepZ / dz if dz != 0 else DBL_MAX

    path, d = [], []
    step = 0
    was_inside = False
    while True:
        inside = (0 <= vx < vxsize) and (0 <= vy < vysize) and (0 <= vz < vzsize)
        if inside:
            was_inside = True
            path.append((vx, vy, vz))
        elif was_inside:
            break
        if tMaxX < tMaxY:
            if tMaxX < tMaxZ:
                _d = tMaxX
                vx += stepX
                tMaxX += tDeltaX
            else:
                _d = tMaxZ
                vz += stepZ
                tMaxZ += tDeltaZ
        else:
            if tMaxY < tMaxZ:
                _d = tMaxY
                vy += stepY
                tMaxY += tDeltaY
            else:
                _d = tMaxZ
                vz += stepZ
                tMaxZ += tDeltaZ
        if inside:
            d.append(_d)
        step += 1
        if step > MAX_STEP:
            break

    if not path:
        return -1.0, (0, 0, 0)
    exp_d, coord = d[-1], path[-1]
    for i, (x, y, z) in enumerate(path):
        if sigma[x][y][z] > 0.5:
            exp_d, coord = d[i], (x, y, z)
            break
    return exp_d, coord


def lidar_rays():
    """``generate_lidar_rays``: float32 [14040, 3]."""
    pitch_angles = [-(math.pi / 2 - math.atan(k + 1)) for k in range(10)]
    while pitch_angles[-1] < 0.21:
        pitch_angles.append(pitch_angles[-1] + (pitch_angles[-1] - pitch_angles[-2]))
    rays = []
    for pitch in pitch_angles:
        for azimuth in np.arange(0, 360, 1):
            azimuth = np.deg2rad(azimuth)
            rays.append((np.cos(pitch) * np.cos(azimuth), np.cos(pitch) * np.sin(azimuth),
                         np.sin(pitch)))
    return np.array(rays, dtype=np.float32)


def process_one_sample(sem, rays, origins, free_id, pc_min=(-40.0, -40.0, -1.0),
                       voxel_size=0.4):
    """[T * D, 2] float32 (label, distance in metres), origin-major, for labels ``sem``."""
    occ = (sem != free_id).tolist()
    offset = np.asarray(pc_min, dtype=np.float32).astype(np.float64)
    scaler = np.float64(np.float32(voxel_size))
    out = []
    for origin in np.asarray(origins, dtype=np.float64):
        endpoints = rays.astype(np.float64) + origin
        o = ((origin - offset) / scaler).astype(np.float32)
        pts = ((endpoints - offset) / scaler).astype(np.float32)
        for p in pts:
            dist, (x, y, z) = render_forward_one_ray(occ, o, p)
            # pred_dist is a float32 tensor, multiplied in place by the voxel size
            dist = np.float32(np.float32(dist) * np.float32(voxel_size))
            out.append((np.float32(sem[x, y, z]), dist))
    return np.array(out, dtype=np.float32).reshape(-1, 2)


def sparseocc_rayiou(preds, gts, origins_list, num_classes=17, rays=None):
    """``main_rayiou`` + ``calc_rayiou``: (iou [3, C], {"RayIoU", "RayIoU@1", "@2", "@4"})."""
    rays = lidar_rays() if rays is None else rays
    free_id = num_classes
    thresholds = [1, 2, 4]
    gt_cnt = np.zeros(num_classes + 1)
    pred_cnt = np.zeros(num_classes + 1)
    tp_cnt = np.zeros((3, num_classes + 1))
    for pred, gt, origins in zip(preds, gts, origins_list):
        pcd_pred = process_one_sample(pred, rays, origins, free_id)
        pcd_gt = process_one_sample(gt, rays, origins, free_id)
        valid = pcd_gt[:, 0].astype(np.int32) != free_id
        pcd_pred, pcd_gt = pcd_pred[valid], pcd_gt[valid]
        for j, threshold in enumerate(thresholds):
            tp_dist = np.abs(pcd_pred[:, 1] - pcd_gt[:, 1]) < threshold
            for c in range(num_classes + 1):
                cls_pred, cls_gt = pcd_pred[:, 0] == c, pcd_gt[:, 0] == c
                if j == 0:
                    gt_cnt[c] += cls_gt.sum()
                    pred_cnt[c] += cls_pred.sum()
                tp_cnt[j][c] += (cls_gt & cls_pred & tp_dist).sum()
    with np.errstate(divide="ignore", invalid="ignore"):
        iou = np.array([(tp_cnt[j] / (gt_cnt + pred_cnt - tp_cnt[j]))[:-1] for j in range(3)])
    result = {"RayIoU": float(np.nanmean(iou))}
    for j, t in enumerate(thresholds):
        result[f"RayIoU@{t}"] = float(np.nanmean(iou[j]))
    return iou, result


def sparseocc_origins(frames, ref_index, max_origins=8, xy_limit=39.0):
    """``EgoPoseDataset.__getitem__`` for frames of one scene in time order, each a pair
    (ego_pose 4x4 global-from-ego, lidar2ego 4x4 ego-from-lidar): origins [T, 3] float64."""
    ego_pose, lidar2ego = (np.asarray(m, dtype=np.float64) for m in frames[ref_index])
    ref_lidar_from_global = np.linalg.inv(ego_pose @ lidar2ego)
    origins = []
    for i, (pose, l2e) in enumerate(frames):
        if i == ref_index:
            origin_tf = np.array([0.0, 0.0, 0.0], dtype=np.float32)
        else:
            global_from_curr = np.asarray(pose, dtype=np.float64) @ np.asarray(l2e, np.float64)
            origin_tf = np.array((ref_lidar_from_global @ global_from_curr)[:3, 3],
                                 dtype=np.float32)
        pad = np.ones(4)
        pad[:3] = origin_tf
        origin_tf = lidar2ego[:3] @ pad
        if abs(origin_tf[0]) < xy_limit and abs(origin_tf[1]) < xy_limit:
            origins.append(origin_tf)
    if len(origins) > max_origins:
        pick = np.round(np.linspace(0, len(origins) - 1, max_origins)).astype(np.int64)
        origins = [origins[i] for i in pick]
    return np.stack(origins)
