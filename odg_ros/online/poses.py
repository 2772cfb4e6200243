"""Ego pose buffer with interpolation at any stamp (odometry -> pose at each camera's stamp).

Poses are ``T_global_from_ego`` 4x4 (geometry.py conventions). Between two buffered poses
the translation is interpolated linearly and the rotation by quaternion slerp, as tf2 does,
when they are at most ``max_interpolation_gap`` apart (the node's ``max_pose_gap``: nuScenes
converters publish poses at keyframes only, 2 Hz, with gaps scattered around 0.5 s). Outside
the buffered interval a pose is extrapolated (same formulas, constant velocity of the two end
poses) only up to ``max_extrapolation`` seconds; farther is a pose miss, never a guess.

A miss is *pending* (``BadInput.pending``) when the pose may still come: nothing received
yet, or the stamp is newer than the newest pose by at most the gap bound (the next pose can
still bracket it). Every other miss is final: a stamp older than the buffer, two neighbours
farther apart than the bound (odometry dropped out), a non-finite stamp, or a stamp more than
the bound beyond the newest pose.

A sample that would make the ego move faster than ``max_speed`` or accelerate harder than
``max_acceleration`` from its neighbours is a glitch: rejected (``implausible_motion``), so it
is never interpolated into a camera pose. Speeds and accelerations are measured between real
samples over at least MIN_MOTION_DT, so a 2 Hz stream is judged by its mean velocities over
0.5-1 s (a real car's stay far below the bounds). A jump that persists (``teleport_samples``
glitches in a row, consistent with each other: relocalisation, a new map) is a teleport: the
buffer starts over from them (``teleports`` counts it).
"""
from __future__ import annotations

import math

import bisect

import numpy as np

from ..geometry import is_rigid, make_transform, matrix_to_quaternion
from ..rotation import slerp
from .errors import BadInput


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

    # Speeds are measured over at least this long: pose noise over a few milliseconds
    # would otherwise look like an impossible speed.
    MIN_MOTION_DT = 0.05

    def __init__(self, capacity: int = 2000, max_extrapolation: float = 0.05,
                 max_interpolation_gap: float = 1.0, time_jump: float = 1.0,
                 max_speed: float = math.inf, max_acceleration: float = math.inf,
                 teleport_samples: int = 3):
        if capacity < 2 or max_extrapolation < 0 or not max_interpolation_gap > 0 \
                or not max_speed > 0 or not max_acceleration > 0 or teleport_samples < 1:
            raise ValueError("bad pose buffer settings")
        self.capacity = int(capacity)
        self.max_extrapolation = float(max_extrapolation)
        self.max_interpolation_gap = float(max_interpolation_gap)
        self.time_jump = float(time_jump)
        self.max_speed = float(max_speed)
        self.max_acceleration = float(max_acceleration)
        self.teleport_samples = int(teleport_samples)
        self._stamps: list[float] = []
        self._poses: list[np.ndarray] = []
        self._suspects: list[tuple[float, np.ndarray]] = []   # consecutive rejected samples
        self.resets = 0
        self.teleports = 0

    def __len__(self) -> int:
        return len(self._stamps)

    def clear(self) -> None:
        self._stamps.clear()
        self._poses.clear()
        self._suspects.clear()

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
        problem = self._implausible(stamp, T)
        if problem is not None:
            self._suspect(stamp, T, problem)
            return
        if self._suspects and stamp > self._suspects[-1][0]:
            self._suspects.clear()      # back on track after a glitch
        self._insert(stamp, T)

    def _insert(self, stamp: float, T: np.ndarray) -> None:
        i = bisect.bisect_left(self._stamps, stamp)
        if i < len(self._stamps) and self._stamps[i] == stamp:
            self._poses[i] = T  # same stamp again: the newer message wins
            return
        self._stamps.insert(i, stamp)
        self._poses.insert(i, T)
        if len(self._stamps) > self.capacity:
            del self._stamps[0]
            del self._poses[0]

    def _suspect(self, stamp: float, T: np.ndarray, problem: str) -> None:
        """A rejected sample: a glitch, or one more step of a teleport that persists."""
        if self._suspects and (stamp <= self._suspects[-1][0] or self._speed_problem(
                *self._suspects[-1], stamp, T) is not None):
            self._suspects.clear()      # not a continuation of the previous suspects
        self._suspects.append((stamp, T))
        if len(self._suspects) >= self.teleport_samples:
            suspects = list(self._suspects)
            self.clear()
            for s, pose in suspects:
                self._insert(s, pose)
            self.teleports += 1
            return
        raise BadInput("implausible_motion", f"pose at t={stamp:.3f} rejected: {problem}")

    def _speed_problem(self, t0: float, T0, t1: float, T1) -> str | None:
        """Why going from (t0, T0) to (t1, T1) is faster than a car, or None."""
        dt = max(abs(t1 - t0), self.MIN_MOTION_DT)
        speed = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3])) / dt
        if not speed <= self.max_speed:
            return f"{speed:.3g} m/s from the pose at t={t0:.3f} (max_speed {self.max_speed})"
        return None

    def _implausible(self, stamp: float, T: np.ndarray) -> str | None:
        """Checks a new sample against its neighbours in time (either arrival order) for
        speed and, when it is the newest, against the velocity before it for acceleration.
        Velocities are taken over at least MIN_MOTION_DT, between real samples."""
        if math.isinf(self.max_speed) and math.isinf(self.max_acceleration):
            return None
        stamps, poses = self._stamps, self._poses
        i = bisect.bisect_left(stamps, stamp)
        j = i + 1 if i < len(stamps) and stamps[i] == stamp else i   # next neighbour
        if i > 0:
            problem = self._speed_problem(stamps[i - 1], poses[i - 1], stamp, T)
            if problem is not None:
                return problem
        if j < len(stamps):
            return self._speed_problem(stamps[j], poses[j], stamp, T)
        a = bisect.bisect_right(stamps, stamp - self.MIN_MOTION_DT) - 1
        b = bisect.bisect_right(stamps, stamps[a] - self.MIN_MOTION_DT) - 1 if a >= 0 else -1
        if b < 0:
            return None
        v_new = (T[:3, 3] - poses[a][:3, 3]) / (stamp - stamps[a])
        v_old = (poses[a][:3, 3] - poses[b][:3, 3]) / (stamps[a] - stamps[b])
        acceleration = float(np.linalg.norm(v_new - v_old)) / (0.5 * (stamp - stamps[b]))
        if not acceleration <= self.max_acceleration:
            return (f"{acceleration:.3g} m/s^2 after the pose at t={stamps[a]:.3f} "
                    f"(max_acceleration {self.max_acceleration})")
        return None

    def lookup(self, stamp: float) -> np.ndarray:
        """``T_global_from_ego`` at ``stamp``; raises ``BadInput('pose_miss')`` if unknown,
        with ``pending`` set when the pose for ``stamp`` may still arrive."""
        stamps = self._stamps
        if not math.isfinite(stamp):
            raise BadInput("pose_miss", f"no pose at a non-finite stamp {stamp}")
        if not stamps:
            raise BadInput("pose_miss", f"no pose received yet (wanted t={stamp:.3f})",
                           pending=True)
        first, last = stamps[0], stamps[-1]
        gap = self.max_interpolation_gap
        if stamp < first - self.max_extrapolation:
            raise BadInput("pose_miss", f"no pose near t={stamp:.3f}: older than the buffer, "
                           f"which spans [{first:.3f}, {last:.3f}]")
        if stamp > last + self.max_extrapolation:
            # pending, however far ahead: poses after a dropout or a jump forward in time (a
            # bag of the next scene) can still bracket it, as tf2 would wait for them
            ahead = stamp - last
            beyond = f" (> max_pose_gap {gap:g} s: only newer poses can give it)" \
                if ahead > gap else ""
            raise BadInput("pose_miss", f"no pose at t={stamp:.3f} yet: the newest is "
                           f"{ahead:.3f} s older{beyond}", pending=True)
        i = bisect.bisect_left(stamps, stamp)
        if i < len(stamps) and stamps[i] == stamp:
            return self._poses[i].copy()
        if len(stamps) == 1:
            return self._poses[0].copy()   # within the bound of the only pose: hold it
        # neighbours (i-1, i) inside; the two end poses when extrapolating
        lo = min(max(i - 1, 0), len(stamps) - 2)
        hi = lo + 1
        if stamps[hi] - stamps[lo] > gap:
            # beyond the newest pose, the next one may still close the gap
            raise BadInput("pose_miss", f"pose gap of {stamps[hi] - stamps[lo]:.3f} s around "
                           f"t={stamp:.3f} (> max_pose_gap {gap:g} s)", pending=stamp > last)
        return interpolate_pose(stamps[lo], self._poses[lo], stamps[hi], self._poses[hi], stamp)
