"""Ego pose buffer with interpolation at any stamp (odometry -> pose at each camera's stamp).

Poses are ``T_global_from_ego`` 4x4 (geometry.py conventions). Between two buffered poses
the translation is interpolated linearly and the rotation by quaternion slerp. Outside the
buffered interval a pose is extrapolated (same formulas, constant velocity of the two end
poses) only up to ``max_extrapolation`` seconds; farther is a pose miss, never a guess. Two
neighbours farther apart than ``max_interpolation_gap`` (odometry dropped out) are a pose
miss too.
"""
from __future__ import annotations

import math

import bisect

import numpy as np

from ..geometry import is_rigid, make_transform, matrix_to_quaternion
from .errors import BadInput


def slerp(q0, q1, alpha: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (w, x, y, z) along the shorter arc.

    ``alpha`` outside [0, 1] continues the rotation at the same angular rate (extrapolation).
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(q0 @ q1)
    if dot < 0.0:           # q and -q are the same rotation; take the short way round
        q1, dot = -q1, -dot
    if dot > 0.9995:        # nearly parallel: sin(theta) ~ 0, normalised lerp is exact enough
        q = q0 + alpha * (q1 - q0)
    else:
        theta = np.arccos(min(dot, 1.0))
        q = (np.sin((1.0 - alpha) * theta) * q0 + np.sin(alpha * theta) * q1) / np.sin(theta)
    return q / np.linalg.norm(q)


def interpolate_pose(t0: float, T0, t1: float, T1, t: float) -> np.ndarray:
    """Pose at ``t`` from poses at ``t0 != t1`` (linear translation + slerp rotation)."""
    alpha = (t - t0) / (t1 - t0)
    T0 = np.asarray(T0, dtype=np.float64)
    T1 = np.asarray(T1, dtype=np.float64)
    q = slerp(matrix_to_quaternion(T0[:3, :3]), matrix_to_quaternion(T1[:3, :3]), alpha)
    translation = T0[:3, 3] + alpha * (T1[:3, 3] - T0[:3, 3])
    return make_transform(q, translation)


def pose_from_xyz_xyzw(translation, quaternion_xyzw) -> np.ndarray:
    """4x4 from a ROS position and a ROS quaternion (x, y, z, w order).

    Raises ``BadInput('bad_pose')`` for non-finite values or a quaternion whose norm is not 1
    (within 1e-3): silently normalising a corrupted quaternion would hide the error.
    """
    t = np.asarray(translation, dtype=np.float64)
    q = np.asarray(quaternion_xyzw, dtype=np.float64)
    if t.shape != (3,) or q.shape != (4,) or not (np.all(np.isfinite(t))
                                                   and np.all(np.isfinite(q))):
        raise BadInput("bad_pose", f"non-finite pose: translation {t}, quaternion {q}")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-3:
        raise BadInput("bad_pose", f"quaternion {q.tolist()} has norm {norm:.4f}, not 1")
    x, y, z, w = q
    return make_transform(np.array([w, x, y, z]), t)


class PoseBuffer:
    """Time-sorted, bounded buffer of ego poses. Not thread-safe; the pipeline locks it."""

    def __init__(self, capacity: int = 2000, max_extrapolation: float = 0.05,
                 max_interpolation_gap: float = 0.5, time_jump: float = 1.0):
        if capacity < 2 or max_extrapolation < 0 or not max_interpolation_gap > 0:
            raise ValueError("bad pose buffer settings")
        self.capacity = int(capacity)
        self.max_extrapolation = float(max_extrapolation)
        self.max_interpolation_gap = float(max_interpolation_gap)
        self.time_jump = float(time_jump)
        self._stamps: list[float] = []
        self._poses: list[np.ndarray] = []
        self.resets = 0

    def __len__(self) -> int:
        return len(self._stamps)

    def clear(self) -> None:
        self._stamps.clear()
        self._poses.clear()

    @property
    def span(self) -> tuple[float, float] | None:
        return (self._stamps[0], self._stamps[-1]) if self._stamps else None

    def add(self, stamp: float, T_global_from_ego) -> None:
        """Insert a pose (any arrival order). Raises ``BadInput('bad_pose')`` on NaN/non-rigid."""
        T = np.asarray(T_global_from_ego, dtype=np.float64)
        stamp = float(stamp)
        if not np.isfinite(stamp):
            raise BadInput("bad_pose", f"non-finite pose stamp {stamp}")
        if not is_rigid(T):
            raise BadInput("bad_pose", "pose is not a finite rigid transform "
                           "(NaN, or rotation not orthonormal with det +1)")
        if self._stamps and stamp < self._stamps[-1] - self.time_jump:
            self.clear()        # time went backwards (bag loop): old poses are another run
            self.resets += 1
        i = bisect.bisect_left(self._stamps, stamp)
        if i < len(self._stamps) and self._stamps[i] == stamp:
            self._poses[i] = T  # same stamp again: the newer message wins
            return
        self._stamps.insert(i, stamp)
        self._poses.insert(i, T)
        if len(self._stamps) > self.capacity:
            del self._stamps[0]
            del self._poses[0]

    def lookup(self, stamp: float) -> np.ndarray:
        """``T_global_from_ego`` at ``stamp``; raises ``BadInput('pose_miss')`` if unknown."""
        stamps = self._stamps
        if not math.isfinite(stamp):
            raise BadInput("pose_miss", f"no pose at a non-finite stamp {stamp}")
        if not stamps:
            raise BadInput("pose_miss", f"no pose received yet (wanted t={stamp:.3f})")
        first, last = stamps[0], stamps[-1]
        if stamp < first - self.max_extrapolation or stamp > last + self.max_extrapolation:
            raise BadInput("pose_miss", f"no pose near t={stamp:.3f}: buffer spans "
                           f"[{first:.3f}, {last:.3f}], extrapolation bound "
                           f"{self.max_extrapolation * 1e3:.0f} ms")
        i = bisect.bisect_left(stamps, stamp)
        if i < len(stamps) and stamps[i] == stamp:
            return self._poses[i].copy()
        if len(stamps) == 1:
            return self._poses[0].copy()   # within the bound of the only pose: hold it
        # neighbours (i-1, i) inside; the two end poses when extrapolating
        lo = min(max(i - 1, 0), len(stamps) - 2)
        hi = lo + 1
        if stamps[hi] - stamps[lo] > self.max_interpolation_gap:
            raise BadInput("pose_miss", f"pose gap of {stamps[hi] - stamps[lo]:.3f} s around "
                           f"t={stamp:.3f} (> {self.max_interpolation_gap} s)")
        return interpolate_pose(stamps[lo], self._poses[lo], stamps[hi], self._poses[hi], stamp)
