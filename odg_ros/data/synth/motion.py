"""Paths and speed profiles of everything that moves, evaluated for all movers at once.

A path is a densely sampled 2D polyline in the city frame (straight pieces and circular
arcs), parameterised by arc length. A speed profile v(t) >= 0 on a fixed time grid is
integrated (trapezoid) into s(t); the pose at time t is the path pose at s(t) and the
velocity is v(t) times the path tangent, so displacements and velocities agree.
"""
from __future__ import annotations

import numpy as np

PATH_STEP = 0.2   # metres between path samples
TIME_STEP = 0.02  # seconds between speed-profile samples


class Path:
    """Arc-length parameterised polyline. ``xy`` [M, 2], ``s`` [M], unwrapped ``yaw`` [M]."""

    def __init__(self, start_xy, start_yaw, pieces):
        """``pieces``: sequence of ("line", length) or ("arc", radius, signed angle; > 0 = left)."""
        x, y, yaw = float(start_xy[0]), float(start_xy[1]), float(start_yaw)
        xs, ys, yaws = [np.array([x])], [np.array([y])], [np.array([yaw])]
        for piece in pieces:
            if piece[0] == "line":
                n = max(1, int(np.ceil(piece[1] / PATH_STEP)))
                d = piece[1] * np.arange(1, n + 1) / n
                px, py, pa = x + d * np.cos(yaw), y + d * np.sin(yaw), np.full(n, yaw)
            elif piece[0] == "arc":
                radius, angle = float(piece[1]), float(piece[2])
                n = max(1, int(np.ceil(abs(angle) * radius / PATH_STEP)))
                sgn = np.sign(angle)
                cx, cy = x - np.sin(yaw) * radius * sgn, y + np.cos(yaw) * radius * sgn
                pa = yaw + angle * np.arange(1, n + 1) / n
                px, py = cx + np.sin(pa) * radius * sgn, cy - np.cos(pa) * radius * sgn
            else:
                raise ValueError(f"unknown path piece {piece!r}")
            xs.append(px), ys.append(py), yaws.append(pa)
            x, y, yaw = float(px[-1]), float(py[-1]), float(pa[-1])
        xs, ys, yaws = np.concatenate(xs), np.concatenate(ys), np.concatenate(yaws)
        self.xy = np.stack([xs, ys], -1)
        self.yaw = np.asarray(yaws)
        seg = np.linalg.norm(np.diff(self.xy, axis=0), axis=1)
        self.s = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.s[-1])


def speed_profile(rng, duration, v_start, v_cruise, v_max, change_every=(3.0, 8.0), accel=1.5,
                  stop_prob=0.0):
    """Speeds [T] on the TIME_STEP grid covering [0, duration]: v approaches piecewise constant
    targets (new target every few seconds, sometimes 0 = a stop) with bounded acceleration."""
    n = int(np.ceil(duration / TIME_STEP)) + 2
    v = np.empty(n)
    cur, target = float(v_start), float(v_cruise)
    next_change = rng.uniform(*change_every)
    for i in range(n):
        t = i * TIME_STEP
        if t >= next_change:
            next_change = t + rng.uniform(*change_every)
            target = 0.0 if rng.random() < stop_prob else min(max(v_cruise * rng.uniform(0.6, 1.3), 0.0), v_max)
        dv = min(max(target - cur, -accel * TIME_STEP), accel * TIME_STEP)
        cur = max(0.0, cur + dv)
        v[i] = cur
    return v


class Movers:
    """All movers of a scene: mover m follows ``paths[m]`` with speeds ``speeds[m]`` [T]
    starting at arc length ``s0[m]`` (negative lag allowed for towed trailers)."""

    def __init__(self, paths: list[Path], speeds: list[np.ndarray], s0):
        self.paths = paths
        n_t = max((len(v) for v in speeds), default=1)
        speeds = [np.pad(v, (0, n_t - len(v)), mode="edge") if len(v) else np.zeros(n_t) for v in speeds]
        self.v = np.stack(speeds) if speeds else np.zeros((0, n_t))
        ds = 0.5 * (self.v[:, 1:] + self.v[:, :-1]) * TIME_STEP
        self.s = np.asarray(s0, float)[:, None] + np.concatenate([np.zeros((len(paths), 1)), np.cumsum(ds, 1)], 1)
        # every path in one monotonic array: mover m's arc lengths are offset by m * BIG
        self._big = 1e6
        self._cat_s = np.concatenate([p.s + m * self._big for m, p in enumerate(paths)]) if paths else np.zeros(0)
        self._cat_xy = np.concatenate([p.xy for p in paths]) if paths else np.zeros((0, 2))
        self._cat_yaw = np.concatenate([p.yaw for p in paths]) if paths else np.zeros(0)
        self._start = np.cumsum([0] + [len(p.s) for p in paths])

    def __len__(self):
        return len(self.paths)

    def arc(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(s [M], speed [M]) at time t (linear interpolation on the time grid)."""
        x = t / TIME_STEP
        i = int(np.clip(np.floor(x), 0, self.s.shape[1] - 2))
        f = x - i
        return (self.s[:, i] * (1 - f) + self.s[:, i + 1] * f,
                self.v[:, i] * (1 - f) + self.v[:, i + 1] * f)

    def pose(self, t: float):
        """City-frame (xy [M, 2], yaw [M], velocity [M, 2]) of every mover at time t.
        Arc lengths beyond a path's ends clamp to the end (the mover waits there)."""
        if not self.paths:
            return np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2))
        s, v = self.arc(t)
        lengths = np.array([p.length for p in self.paths])
        s = np.clip(s, 0, lengths)
        key = s + np.arange(len(self.paths)) * self._big
        j = np.searchsorted(self._cat_s, key, side="right") - 1
        j = np.clip(j, self._start[:-1], self._start[1:] - 2)
        s0, s1 = self._cat_s[j], self._cat_s[j + 1]
        f = np.clip((key - s0) / np.maximum(s1 - s0, 1e-12), 0, 1)
        xy = self._cat_xy[j] * (1 - f)[:, None] + self._cat_xy[j + 1] * f[:, None]
        yaw = self._cat_yaw[j] * (1 - f) + self._cat_yaw[j + 1] * f
        seg = self._cat_xy[j + 1] - self._cat_xy[j]
        tangent = seg / np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-12)
        moving = (s > 0) & (s < lengths)
        vel = tangent * (v * moving)[:, None]
        return xy, yaw, vel
