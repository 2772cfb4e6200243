"""Keeps the traffic free of collisions: a thing that would overlap the ego, a static
obstacle or a thing kept before it, at any time of the scene, is left out."""
from __future__ import annotations

import numpy as np

from ..motion import Movers
from .road_grid import Layout


def _circles(shape_wlh, xy, yaw):
    """Footprint discs [..., k, 2] and radius of boxes at poses xy [..., 2], yaw [...]."""
    w, l = shape_wlh[0], shape_wlh[1]
    k = max(1, int(np.ceil(l / w)))
    offs = (np.arange(k) + 0.5) / k * l - l / 2
    c = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    centres = xy[..., None, :] + offs[:, None] * c[..., None, :]
    radius = np.hypot(w / 2, l / (2 * k))
    return centres, radius


def resolve_collisions(layout: Layout, ego_path, ego_speed, duration, ego_wlh=(1.85, 4.6)):
    """Drop things (and their towed partners) that would overlap the ego, a static obstacle
    or a thing kept earlier, at any time of the scene. Returns the kept things."""
    times = np.arange(0, duration + 1e-9, 0.25)
    ego = Movers([ego_path], [ego_speed], [0.0])
    poses = [ego.pose(t) for t in times]
    ego_yaw = np.array([p[1][0] for p in poses])
    # base_link is the rear axle; the car's centre is ~1.4 m ahead
    ego_xy = np.array([p[0][0] for p in poses]) + 1.4 * np.stack([np.cos(ego_yaw), np.sin(ego_yaw)], -1)
    c, r = _circles(ego_wlh, ego_xy, ego_yaw)
    kept = [(c, np.full(c.shape[1], r))]
    if layout.obstacles:
        obs = np.array(layout.obstacles)
        for o in obs:
            kept.append((np.broadcast_to(o[None, None, :2], (len(times), 1, 2)), o[2:3]))
    everyone = Movers([t[1] for t in layout.things], [t[2] for t in layout.things], [t[3] for t in layout.things])
    all_poses = [everyone.pose(t) for t in times]
    xy_all = np.stack([p[0] for p in all_poses], 1)    # [N, T, 2]
    yaw_all = np.stack([p[1] for p in all_poses], 1)   # [N, T]
    groups = {}
    for i, th in enumerate(layout.things):
        groups.setdefault(th[5] if th[5] is not None else ("solo", i), []).append(i)

    def bbox(cc, rr):
        return np.concatenate([cc.reshape(-1, 2).min(0) - rr.max(), cc.reshape(-1, 2).max(0) + rr.max()])

    kept_box = np.array([bbox(cc, rr) for cc, rr in kept])
    keep = []
    for members in groups.values():
        cs, rs = [], []
        for i in members:
            cc, rr = _circles(layout.things[i][0].wlh, xy_all[i], yaw_all[i])
            cs.append(cc)
            rs.append(np.full(cc.shape[1], rr))
        cand_c, cand_r = np.concatenate(cs, 1), np.concatenate(rs)
        box = bbox(cand_c, cand_r)
        overlap = np.flatnonzero((kept_box[:, 0] < box[2] + 0.3) & (kept_box[:, 2] > box[0] - 0.3)
                                 & (kept_box[:, 1] < box[3] + 0.3) & (kept_box[:, 3] > box[1] - 0.3))
        hit = False
        for k in overlap:
            kc, kr = kept[k]
            d = np.linalg.norm(cand_c[:, :, None, :] - kc[:, None, :, :], axis=-1)
            if np.any(d < cand_r[None, :, None] + kr[None, None, :] + 0.3):
                hit = True
                break
        if hit:
            continue
        keep.extend(members)
        kept.append((cand_c, cand_r))
        kept_box = np.concatenate([kept_box, box[None]])
    return [layout.things[i] for i in sorted(keep)]
