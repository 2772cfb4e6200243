"""Approximate-time synchronisation of the cameras into sets (one set = one network input).

The six nuScenes images of one set span ~42 ms and two sets mixed span >= ~74 ms
(docs/architecture.md sec. 2), so a set is a group of one message per camera whose stamps span at
most ``slop`` seconds (0.05 by default).

Messages are fed one by one as ``(camera, stamp, payload)``; arrival order is free
(jitter, reordering between and within sets). Rules, all deterministic:

* A message joins the pending set that lacks its camera and stays within ``slop`` with it;
  otherwise it opens a new pending set. If several fit, it joins the one whose reference
  stamp is closest to its own, a message's reference stamp being its stamp minus its camera's
  offset from the reference (first) camera in the last emitted set (0 before the first).
  The slop is wider than the gap between two sets (nuScenes: the last camera fires ~41 ms
  before the next set's first), so the last camera of a set also fits the first cameras of
  the next one; by stamps alone it could join them, leaving both sets incomplete and a third
  partial set (counted dropped_incomplete: one set counted twice).
* A message whose camera already has exactly that stamp in a pending set is a duplicate
  (dropped, counted).
* When a set becomes complete it is emitted; every pending set older than it can no longer
  be emitted in order, so it is dropped and counted as ``dropped_incomplete``.
* A message not newer than the last emitted set is late (its set is gone): dropped, counted.
  One more than ``time_jump`` seconds older than the newest stamp seen is a time jump
  (a bag restarted): everything pending is cleared and synchronisation starts over. Until the
  first set after the jump is emitted, a message more than ``time_jump`` ahead of the new
  stamps and not newer than the newest stamp before the jump is from before it (an executor
  takes one message per topic at a time, so a camera's last old message can follow another
  camera's first new one): late, not a new set that would jump the clock back again.
* At most ``max_pending`` sets wait; opening one more drops the oldest (a dead camera
  therefore costs bounded memory, and shows up in ``dropped_incomplete``). The rest of a set
  dropped that way is late when it comes (a lagging camera's backlog, however many sets
  behind, up to ``time_jump``): a set is emitted or dropped once, never dropped again as a new
  partial set.
"""
from __future__ import annotations

import math

from dataclasses import dataclass, field
from typing import Any, Sequence

from .errors import BadInput


def stamp_to_seconds(sec: int, nanosec: int) -> float:
    """A ``builtin_interfaces/Time`` in seconds; raises ``BadInput('bad_stamp')`` for one that
    is no valid time (nanosec outside [0, 1e9)), which a reply would otherwise repeat."""
    if not 0 <= nanosec < 1_000_000_000:
        raise BadInput("bad_stamp", f"header stamp sec={sec}, nanosec={nanosec}: nanosec "
                       "must be in [0, 1e9)")
    return sec + nanosec * 1e-9


@dataclass
class CameraSet:
    """One message per camera. ``stamps``/``payloads`` are keyed by camera name, in the
    configured camera order."""

    stamps: dict[str, float]
    payloads: dict[str, Any]
    completed_at: float | None = None      # steady clock, when its last message came
    waited: float = 0.0       # seconds it waited for its poses / extrinsics (waiting.py)
    expired: bool = False     # handed on because that wait ran out
    looked_up: Any = None     # its look-ups, done while deciding it was ready (pipeline.py)

    @property
    def reference_camera(self) -> str:
        """The first configured camera (CAM_FRONT): the set's ego frame is the ego at its
        stamp, as for the history frames of the dataset (data/dataset.py)."""
        return next(iter(self.stamps))

    @property
    def reference_stamp(self) -> float:
        return self.stamps[self.reference_camera]

    @property
    def span(self) -> float:
        return max(self.stamps.values()) - min(self.stamps.values())


@dataclass
class _Pending:
    stamps: dict[str, float] = field(default_factory=dict)
    payloads: dict[str, Any] = field(default_factory=dict)

    @property
    def low(self) -> float:
        return min(self.stamps.values())

    @property
    def high(self) -> float:
        return max(self.stamps.values())


class CameraSetSync:
    """Groups camera messages into complete sets. Not thread-safe: call from one thread."""

    COUNTERS = ("sets_emitted", "dropped_incomplete", "late_messages", "duplicate_messages",
                "time_jumps")

    def __init__(self, camera_names: Sequence[str], slop: float = 0.05, max_pending: int = 8,
                 time_jump: float = 1.0):
        if len(set(camera_names)) != len(camera_names) or not camera_names:
            raise ValueError(f"camera names must be unique and non-empty: {camera_names}")
        if not slop > 0 or max_pending < 1 or not time_jump > slop:
            raise ValueError(f"bad sync settings: slop={slop}, max_pending={max_pending}, "
                             f"time_jump={time_jump}")
        self.camera_names = tuple(camera_names)
        self.slop = float(slop)
        self.max_pending = int(max_pending)
        self.time_jump = float(time_jump)
        self.counters = {name: 0 for name in self.COUNTERS}
        self._pending: list[_Pending] = []
        self._last_emitted: float | None = None   # newest stamp of the last emitted set
        self._newest_seen: float | None = None
        self._evicted: list[tuple[float, float]] = []  # (low, high) of sets dropped for room
        self._newest_before_jump: float | None = None
        # camera -> its stamp minus the reference camera's in the last emitted set (the rig's
        # firing pattern: kept across a reset)
        self._offsets: dict[str, float] = {}

    def reset(self) -> None:
        self._pending.clear()
        self._evicted.clear()
        self._last_emitted = None
        self._newest_seen = None
        self._newest_before_jump = None

    @property
    def num_pending(self) -> int:
        return len(self._pending)

    def add(self, camera: str, stamp: float, payload: Any) -> list[CameraSet]:
        """Feed one message; returns the sets it completed (zero or one, oldest first)."""
        if camera not in self.camera_names:
            raise ValueError(f"unknown camera {camera!r}; expected one of {self.camera_names}")
        stamp = float(stamp)
        if not math.isfinite(stamp):
            raise ValueError(f"{camera}: non-finite stamp {stamp}")
        if self._newest_seen is not None and stamp < self._newest_seen - self.time_jump:
            self.counters["time_jumps"] += 1
            self.counters["dropped_incomplete"] += len(self._pending)  # cannot complete now
            newest_before = self._newest_seen
            self.reset()
            self._newest_before_jump = newest_before
        if self._last_emitted is not None and stamp <= self._last_emitted:
            self.counters["late_messages"] += 1
            return []
        if (self._newest_before_jump is not None and self._newest_seen is not None
                and self._newest_seen + self.time_jump < stamp
                <= self._newest_before_jump + self.slop):
            self.counters["late_messages"] += 1  # from before the jump, taken after it
            return []
        self._newest_seen = stamp if self._newest_seen is None else max(self._newest_seen, stamp)

        target = self._best_pending(camera, stamp)
        if target is None:
            if any(p.stamps.get(camera) == stamp for p in self._pending):
                self.counters["duplicate_messages"] += 1
                return []
            if any(max(high, stamp) - min(low, stamp) <= self.slop for low, high in self._evicted):
                self.counters["late_messages"] += 1  # its set was dropped for room
                return []
            target = _Pending()
            self._pending.append(target)
        target.stamps[camera] = stamp
        target.payloads[camera] = payload
        self._pending.sort(key=lambda p: p.low)

        if len(target.stamps) == len(self.camera_names):
            return [self._emit(target)]
        while len(self._pending) > self.max_pending:
            evicted = self._pending.pop(0)
            self._evicted.append((evicted.low, evicted.high))
            self.counters["dropped_incomplete"] += 1
        # a message older than these would be a time jump: bounded memory for a dead camera
        self._evicted = [span for span in self._evicted
                         if span[1] >= self._newest_seen - self.time_jump]
        return []

    def _best_pending(self, camera: str, stamp: float) -> _Pending | None:
        best, best_distance = None, None
        for pending in self._pending:
            if camera in pending.stamps:
                continue
            low, high = min(pending.low, stamp), max(pending.high, stamp)
            if high - low > self.slop:
                continue
            reference = sum(s - self._offsets.get(c, 0.0) for c, s in pending.stamps.items())
            distance = abs(stamp - self._offsets.get(camera, 0.0)
                           - reference / len(pending.stamps))
            if best is None or distance < best_distance:
                best, best_distance = pending, distance
        return best

    def _emit(self, complete: _Pending) -> CameraSet:
        older = [p for p in self._pending if p is not complete and p.low < complete.low]
        self.counters["dropped_incomplete"] += len(older)
        self._pending = [p for p in self._pending if p is not complete and p not in older]
        # Pending sets that overlap the emitted one in time cannot be emitted in order either.
        stale = [p for p in self._pending if p.low <= complete.high]
        self.counters["dropped_incomplete"] += len(stale)
        self._pending = [p for p in self._pending if p not in stale]
        self._last_emitted = complete.high
        self._newest_before_jump = None
        # Sets dropped for room before this one: their messages are now late by stamp alone.
        self._evicted = [span for span in self._evicted if span[1] > complete.high]
        self.counters["sets_emitted"] += 1
        order = self.camera_names
        self._offsets = {c: complete.stamps[c] - complete.stamps[order[0]] for c in order}
        return CameraSet(stamps={c: complete.stamps[c] for c in order},
                         payloads={c: complete.payloads[c] for c in order})
