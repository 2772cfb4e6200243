"""A small TF buffer (the content of /tf and /tf_static) without tf2_ros.

tf2_ros has no PyPI wheel, and the node needs only two kinds of lookups: the ego pose
(e.g. map -> base_link, possibly through odom) at each camera stamp and the camera
extrinsics (base_link -> camera frame, usually static). This buffer keeps the transform
tree the TF messages describe (one parent per child, as TF requires) and composes the edges
along the path between two frames, each at the requested stamp. Thread-safe.

What a hostile or busy TF tree cannot do to it (tf2's rules where tf2 has one):

* a link that would close a loop is rejected (``bad_tf``); the rest of the tree stays usable;
* a frame's static and dynamic transforms are kept apart: a static transform stays valid for
  good, a dynamic one (a PoseBuffer: interpolation across at most ``max_interpolation_gap``,
  the no-extrapolation bound and the motion plausibility checks of odometry) lives as long as
  it is updated, and the static one wins where both exist, so a stray dynamic copy of a
  static link never replaces it;
* a dynamic frame not updated for ``cache_time`` seconds (the buffer's duration, tf2's 10 s)
  is forgotten, and at most ``max_static_frames`` static frames are kept: memory is bounded
  whatever frame names arrive;
* with ``wanted`` frames set (the frames looked up from: the ego frame and the camera frames),
  only the dynamic transforms on their chains up the tree are converted and stored; every
  other one is dropped by its child frame name before any arithmetic (``wants``) and counted
  in ``counters['tf_ignored']``. ``keep_children_of`` keeps the direct children of a frame as
  well (base_link -> every sensor: a camera's frame is known from its CameraInfo, which can
  come after the first /tf that carries it).

A lookup that fails only because its data has not arrived yet (frames not connected yet, or
a dynamic edge's stamp newer than its newest transform, within the gap bound) raises a
*pending* BadInput (``BadInput.pending``): the caller may wait for more TF, as tf2's message
filter does.
"""
from __future__ import annotations

import math
import threading
import time

import numpy as np

from ..geometry import invert_transform, is_rigid
from .errors import BadInput
from .poses import PoseBuffer

MAX_DEPTH = 64      # deeper than any real TF tree; a longer walk means a loop


class TransformBuffer:
    def __init__(self, max_extrapolation: float = 0.05, time_jump: float = 1.0,
                 capacity: int = 2000, cache_time: float = 10.0, max_static_frames: int = 1000,
                 max_speed: float = math.inf, max_acceleration: float = math.inf,
                 wanted=None, clock=time.monotonic, max_interpolation_gap: float = 1.0):
        if not max_interpolation_gap > 0:
            raise ValueError(f"max_interpolation_gap must be > 0, got {max_interpolation_gap}")
        self.max_extrapolation = max_extrapolation
        self.max_interpolation_gap = float(max_interpolation_gap)
        self.time_jump = time_jump
        self.capacity = capacity
        self.cache_time = float(cache_time)
        self.max_static_frames = int(max_static_frames)
        self.max_speed = max_speed
        self.max_acceleration = max_acceleration
        self._clock = clock
        self._static: dict[str, tuple[str, np.ndarray]] = {}    # child -> (parent, T)
        # child -> [parent, buffer of T_parent_from_child, clock of the last update]
        self._dynamic: dict[str, list] = {}
        self._wanted: frozenset[str] | None = None
        self._needed: frozenset[str] | None = None      # child frames whose edges we keep
        self._parents: frozenset[str] = frozenset()      # ... and every child of these
        self._last_prune = clock()
        self.counters = {"tf_received": 0, "tf_ignored": 0, "tf_frames_forgotten": 0,
                         "pose_teleports": 0}
        self._lock = threading.Lock()
        if wanted is not None:
            self.set_wanted(wanted)

    # ------------------------------------------------------------------------ filtering
    def set_wanted(self, frames) -> None:
        """The frames lookups start from (None: keep every transform)."""
        with self._lock:
            wanted = None if frames is None else frozenset(frames)
            if wanted != self._wanted:
                self._wanted = wanted
                self._update_needed()

    def keep_children_of(self, frames) -> None:
        """Keep every dynamic transform whose parent is one of ``frames`` too."""
        self._parents = frozenset(frames)

    def wants(self, child: str, parent: str | None = None) -> bool:
        """Whether a dynamic transform ``parent`` -> ``child`` is worth converting (cheap, no
        lock: a frozenset read is atomic). Counts the ones that are not."""
        needed = self._needed
        self.counters["tf_received"] += 1
        if needed is None or child in needed or parent in self._parents:
            return True
        self.counters["tf_ignored"] += 1
        return False

    def _update_needed(self) -> None:
        if self._wanted is None:
            self._needed = None
            return
        needed = set()
        for frame in self._wanted:
            for _ in range(MAX_DEPTH):
                if frame in needed:
                    break
                needed.add(frame)
                frame = self._parent_of(frame)
                if frame is None:
                    break
        self._needed = frozenset(needed)

    # --------------------------------------------------------------------------- adding
    def _parent_of(self, child: str) -> str | None:
        if child in self._static:
            return self._static[child][0]
        edge = self._dynamic.get(child)
        return edge[0] if edge is not None else None

    def _closes_loop(self, parent: str, child: str) -> bool:
        frame = parent
        for _ in range(MAX_DEPTH):
            if frame == child:
                return True
            frame = self._parent_of(frame)
            if frame is None:
                return False
        return True

    def add(self, parent: str, child: str, stamp: float, T_parent_from_child,
            static: bool = False) -> None:
        """One transform of a TFMessage. Raises BadInput: 'bad_pose' if it is not rigid,
        'bad_tf' if it would close a loop, 'implausible_motion' for a glitch sample."""
        T = np.asarray(T_parent_from_child, dtype=np.float64)
        if not parent or not child or parent == child:
            raise BadInput("bad_tf", f"transform with frames {parent!r} -> {child!r}")
        if not is_rigid(T):
            raise BadInput("bad_pose", f"transform {parent} -> {child} is not a finite rigid "
                           "transform")
        with self._lock:
            now = self._clock()
            if now - self._last_prune > min(1.0, self.cache_time):
                self._forget_stale(now)
            if self._closes_loop(parent, child):
                raise BadInput("bad_tf", f"link {parent} -> {child} would close a loop "
                               "(rejected; the tree keeps its other links)")
            if static:
                if child not in self._static and len(self._static) >= self.max_static_frames:
                    self.counters["tf_ignored"] += 1
                    return
                self._static[child] = (parent, T)
            else:
                edge = self._dynamic.get(child)
                if edge is None or edge[0] != parent:
                    # a new frame, or TF re-parented it: its edge starts over
                    edge = self._dynamic[child] = [parent, PoseBuffer(
                        self.capacity, self.max_extrapolation,
                        max_interpolation_gap=self.max_interpolation_gap,
                        time_jump=self.time_jump, max_speed=self.max_speed,
                        max_acceleration=self.max_acceleration), now]
                edge[2] = now
                buffer = edge[1]
                teleports = buffer.teleports
                try:
                    buffer.add(stamp, T)
                finally:
                    self.counters["pose_teleports"] += buffer.teleports - teleports
            if self._needed is not None and parent not in self._needed:
                self._update_needed()

    def _forget_stale(self, now: float) -> None:
        stale = [c for c, edge in self._dynamic.items() if now - edge[2] > self.cache_time]
        for child in stale:
            del self._dynamic[child]
        self.counters["tf_frames_forgotten"] += len(stale)
        self._last_prune = now
        if stale:
            self._update_needed()

    def frames(self) -> set[str]:
        with self._lock:
            return self._frames_unlocked()

    def _frames_unlocked(self) -> set[str]:
        frames = set(self._static) | set(self._dynamic)
        frames |= {p for p, _ in self._static.values()} | {e[0] for e in self._dynamic.values()}
        return frames

    # -------------------------------------------------------------------------- lookups
    def _chain_to_root(self, frame: str) -> list[str]:
        chain = [frame]
        parent = self._parent_of(frame)
        while parent is not None:
            chain.append(parent)
            if len(chain) > MAX_DEPTH:     # add() rejects loops; this only bounds the walk
                raise BadInput("bad_tf", f"TF chain from {frame!r} deeper than {MAX_DEPTH}")
            parent = self._parent_of(parent)
        return chain

    def _root_from(self, chain: list[str], stamp: float, kind: str) -> np.ndarray:
        """T_root_from_chain[0] at ``stamp`` (composition along the chain). An edge that
        fails for good is raised at once, before one whose data may still come."""
        T = np.eye(4)
        pending = None
        for child in chain[:-1]:
            if child in self._static:
                edge = self._static[child][1]
            else:
                parent, buffer, _ = self._dynamic[child]
                try:
                    edge = buffer.lookup(stamp)
                except BadInput as error:
                    error = BadInput(kind, f"TF {parent} -> {child}: {error.message}",
                                     pending=error.pending)
                    if not error.pending:
                        raise error from None
                    pending = pending or error
                    continue
            T = edge @ T
        if pending is not None:
            raise pending
        return T

    def _common_frame(self, target: str, source: str):
        """(the chains of source and target up to the tree's root, their first common frame
        or None)."""
        up_source = self._chain_to_root(source)
        up_target = self._chain_to_root(target)
        targets = set(up_target)
        return up_source, up_target, next((f for f in up_source if f in targets), None)

    def connected(self, target: str, source: str) -> bool:
        """Whether a TF path joins the two frames now (at some stamp, not necessarily every
        one)."""
        with self._lock:
            return target == source or self._common_frame(target, source)[2] is not None

    def lookup(self, target: str, source: str, stamp: float,
               kind: str = "pose_miss") -> np.ndarray:
        """T_target_from_source at ``stamp``; raises BadInput(kind) if not connected/known
        (pending: frames not connected yet, or a stamp beyond a dynamic edge's newest)."""
        with self._lock:
            if target == source:
                return np.eye(4)
            up_source, up_target, common = self._common_frame(target, source)
            if common is None:
                known = sorted(self._frames_unlocked())
                shown = ", ".join(known[:20]) + (f", ... ({len(known)} in all)"
                                                 if len(known) > 20 else "")
                raise BadInput(kind, f"no TF path between {target!r} and {source!r} "
                               f"(known frames: {shown or 'none'})", pending=True)
            to_common_source = up_source[:up_source.index(common) + 1]
            to_common_target = up_target[:up_target.index(common) + 1]
            try:
                common_from_source = self._root_from(to_common_source, stamp, kind)
            except BadInput as error:
                if error.pending:        # a final failure of the other chain comes first
                    self._root_from(to_common_target, stamp, kind)
                raise
            common_from_target = self._root_from(to_common_target, stamp, kind)
            return invert_transform(common_from_target) @ common_from_source
