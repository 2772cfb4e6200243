"""Latest-wins single-slot mailbox between the ROS callbacks and the inference worker.

When inference is slower than the cameras, queueing sets would grow latency without bound;
instead a new set replaces the one still waiting (which is counted as ``dropped``), so the
worker always starts on the freshest set and latency stays at most one inference long.
"""
from __future__ import annotations

import threading
from typing import Any


class HandOff:
    """What a hand-off between threads has: one condition, and a close that wakes the
    consumer for good."""

    def __init__(self):
        self._condition = threading.Condition()
        self._closed = False

    def close(self) -> None:
        """Wake the consumer for good (shutdown); later ``get`` calls return None at once."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed


class LatestMailbox(HandOff):
    """Thread-safe: ``put`` from any thread, ``get`` from the worker."""

    def __init__(self):
        super().__init__()
        self._item: Any = None
        self._full = False
        self.dropped = 0    # items replaced before the worker took them
        self.delivered = 0

    def put(self, item: Any) -> bool:
        """Store ``item``; returns True if it replaced an untaken one (that one is dropped)."""
        with self._condition:
            replaced = self._full
            if replaced:
                self.dropped += 1
            self._item, self._full = item, True
            self._condition.notify()
            return replaced

    def get(self, timeout: float | None = None) -> Any:
        """The newest item, waiting up to ``timeout`` s; None on timeout or after ``close``."""
        with self._condition:
            if not self._condition.wait_for(lambda: self._full or self._closed, timeout):
                return None
            if not self._full:
                return None
            item, self._item, self._full = self._item, None, False
            self.delivered += 1
            return item
