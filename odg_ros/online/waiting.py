"""Complete camera sets waiting for their poses, extrinsics and first CameraInfo, newest
ready set first.

A set can complete before the poses (or camera transforms) for its stamps have arrived:
nuScenes bag converters publish /tf only at 2 Hz keyframes (a set between two keyframes needs
the next one's transform) or write odometry in bursts up to 0.5 s after the stamps it
carries. As tf2's message filter does, such a set waits, bounded, instead of being dropped.
So does a set completed before the first CameraInfo of one of its cameras was read (a player
publishes each CameraInfo next to its image; the node's callbacks run in their own order).

``probe(item, final)`` tells whether a set is READY (its look-ups succeed), FAILED (they fail
for good) or PENDING (they only wait for data not received yet). The consumer (``get``)
takes, in this order:

* a failed set newer than the newest ready one, on its own (the consumer counts the failure
  under its own name: a gap too wide, a stamp older than the buffer...);
* the newest ready set; every older set is dropped and counted stale (``dropped``), as the
  latest-wins mailbox does: the newest data wins, and the history stays in stamp order;
* else the oldest set that has waited ``wait`` seconds, on its own, probed one last time
  with ``final=True`` (where a source may settle, e.g. extrinsics falling back to the rig
  file) and marked ``expired``, so the consumer counts it as the miss it is;
* else nothing yet: it sleeps until a new set or new pose data (``notify``) or a short poll.

Which clock measures the wait: the node's (``clock``), so that with ``use_sim_time`` and a
replayed bag the wait is in bag time, whatever the replay rate; the steady clock while the
node's clock does not run (0: sim time before the first /clock). A set never waits forever:
when the node's clock stands still (the replay ended or was paused; what the set waits for
comes with that clock, so not before it moves again), the steady seconds a set has waited
since the clock stopped count too, and it expires after ``wait`` of them. A set whose node
clock went backwards past its arrival (the bag looped) is dropped as stale, and so is every
waiting set when a set older than them arrives (synchronisation restarted after a time jump):
neither can be processed in stamp order any more.

At most ``capacity`` sets wait (16: over a second of 12 Hz cameras); one more drops the
oldest as stale, which costs nothing the rule above would not drop anyway.

Thread-safe: ``put`` and ``notify`` from the input callbacks (they never wait for a probe),
``get`` from one consumer thread; probes run outside the lock.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from .mailbox import HandOff


READY, FAILED, PENDING = "ready", "failed", "pending"

# The node clock going back by more than this (s) is a jump (a bag looped), not jitter between
# the callbacks' and the consumer's readings of it.
CLOCK_JUMP = 1.0


@dataclass
class _Entry:
    item: Any
    stamp: float
    node_start: float
    steady_start: float
    probes: int = field(default=0)
    expired: bool = field(default=False)


class WaitingSets(HandOff):
    def __init__(self, probe: Callable[[Any, bool], str], wait: float,
                 clock: Callable[[], float] | None = None, capacity: int = 16,
                 poll: float = 0.05, steady: Callable[[], float] = time.monotonic,
                 stamp_of: Callable[[Any], float] = lambda item: item.reference_stamp):
        if not wait >= 0 or capacity < 1 or not poll > 0:
            raise ValueError(f"bad waiting settings: wait={wait}, capacity={capacity}, "
                             f"poll={poll}")
        self._probe = probe
        self.wait = float(wait)
        self._clock = clock if clock is not None else (lambda: 0.0)
        self._steady = steady
        self._stamp_of = stamp_of
        self.capacity = int(capacity)
        self.poll = float(poll)
        super().__init__()
        self._entries: list[_Entry] = []        # ascending stamps
        self._news = 0                          # puts and notifies: probe only after news
        self.dropped = 0     # stale: a newer set was taken first, or no longer in stamp order
        self.delivered = 0
        self.waited = 0      # sets handed on after waiting
        self.expired = 0     # sets handed on because their wait ran out
        # the node clock's last reading, and the steady time it was first read at that value
        self._clock_lock = threading.Lock()
        self._last_clock = (None, 0.0)

    # ------------------------------------------------------------------------ producers
    def put(self, item: Any) -> None:
        """A newly completed set."""
        node_now, steady_now, _ = self._now()
        entry = _Entry(item, float(self._stamp_of(item)), node_now, steady_now)
        with self._condition:
            if self._entries and entry.stamp <= self._entries[-1].stamp:
                # synchronisation restarted (the stamps jumped back): the waiting sets come
                # from before the jump and can no longer be processed in order
                self.dropped += len(self._entries)
                self._entries.clear()
            self._entries.append(entry)
            if len(self._entries) > self.capacity:
                del self._entries[0]
                self.dropped += 1
            self._news += 1
            self._condition.notify_all()

    def notify(self) -> None:
        """New poses, transforms or a first CameraInfo arrived: a waiting set may be ready
        now."""
        with self._condition:
            if self._entries:
                self._news += 1
                self._condition.notify_all()

    # ------------------------------------------------------------------------- consumer
    def get(self, timeout: float | None = None) -> Any:
        """The next set to prepare (see the module doc), waiting up to ``timeout`` seconds
        (steady) for one; None on timeout or after ``close``. One consumer at a time. A set
        handed on after waiting carries ``waited`` (seconds) and ``expired`` (True when its
        wait ran out) where it has such attributes."""
        deadline = None if timeout is None else self._steady() + timeout
        seen = -1
        while True:
            with self._condition:
                if self._closed:
                    return None
                self._drop_from_before_a_clock_jump()
                snapshot, news = list(self._entries), self._news
            # news seen even with no set waiting: else the wait below is skipped and the
            # consumer spins, holding the GIL the model's thread needs
            probe, seen = news != seen, news
            if snapshot:
                chosen, newest_ready = self._choose(snapshot, probe=probe)
                if chosen is not None:
                    with self._condition:
                        if chosen in self._entries:   # not cleared by a time jump meanwhile
                            return self._take(chosen, newest_ready)
                    continue
            with self._condition:
                if self._closed:
                    return None
                remaining = None if deadline is None else deadline - self._steady()
                if remaining is not None and remaining <= 0:
                    return None
                if self._news == seen:
                    # woken by a new set or new pose data; polled while sets wait (expiry)
                    limit = self.poll if self._entries else remaining
                    if remaining is not None and limit is not None:
                        limit = min(limit, remaining)
                    self._condition.wait(limit)

    def _choose(self, snapshot: list[_Entry], probe: bool) -> tuple[_Entry | None, bool]:
        """(the entry to hand on or None, whether it is the newest ready one: the older are
        stale then). Outside the lock: probes may take a while."""
        if probe:
            failed = None
            for entry in reversed(snapshot):                 # the newest ready set wins
                entry.probes += 1
                state = self._probe(entry.item, False)
                if state == READY:
                    return (failed, False) if failed is not None else (entry, True)
                if state == FAILED:
                    failed = entry                            # the oldest newer one first
            if failed is not None:
                return failed, False
        now = self._now()
        for entry in snapshot:                                # oldest first
            if self._waited(entry, now) >= self.wait:
                self._probe(entry.item, True)                # last chance (a source settles)
                entry.expired = True
                return entry, False
        return None, False

    def _take(self, chosen: _Entry, newest_ready: bool) -> Any:
        """Under the lock: hand ``chosen`` on; if it is the newest ready set, drop the sets
        older than it as stale."""
        index = self._entries.index(chosen)
        if newest_ready:
            self.dropped += index
            del self._entries[:index + 1]
        else:
            del self._entries[index]
        self.delivered += 1
        if chosen.probes > 1 or chosen.expired:
            self.waited += 1
            self.expired += chosen.expired
            for name, value in (("waited", self._waited(chosen, self._now())),
                                ("expired", chosen.expired)):
                if hasattr(chosen.item, name):
                    setattr(chosen.item, name, value)
        return chosen.item

    def _drop_from_before_a_clock_jump(self) -> None:
        """Under the lock: sets that arrived at a node-clock time well after now (the clock
        went back: the bag looped) are stale."""
        node_now = self._node_now()
        if node_now > 0 and self._entries:
            kept = [e for e in self._entries if not e.node_start > node_now + CLOCK_JUMP]
            self.dropped += len(self._entries) - len(kept)
            self._entries = kept

    # ------------------------------------------------------------------------ reporting
    def __len__(self) -> int:
        with self._condition:
            return len(self._entries)

    # ---------------------------------------------------------------------------- clock
    def _node_now(self) -> float:
        return float(self._clock())

    def _now(self) -> tuple[float, float, float]:
        """(node clock, steady clock, steady seconds the node clock has stood still: since
        its reading last changed)."""
        node_now, steady_now = self._node_now(), self._steady()
        with self._clock_lock:
            value, since = self._last_clock
            if node_now != value:
                self._last_clock = (node_now, steady_now)
                return node_now, steady_now, 0.0
        return node_now, steady_now, steady_now - since

    @staticmethod
    def _waited(entry: _Entry, now: tuple[float, float, float]) -> float:
        """Seconds waited: on the node's clock where it ran at both ends, else steady; or the
        steady seconds waited while the node's clock stood still, if more."""
        node_now, steady_now, still = now
        steady_waited = steady_now - entry.steady_start
        if entry.node_start > 0 and node_now > 0:
            return max(node_now - entry.node_start, min(still, steady_waited))
        return steady_waited
