"""When the decoding thread starts on the next camera set: just before the inference thread
will want it.

Decoding ahead (pipeline.start_decoding) used to decode every set as it arrived. A node
slower than its cameras then decoded several sets per output and dropped all but the newest,
and that decoding ran on the cores the model needed (odg_cpu on 2 cores, sets at 6 per second:
about five decodes per grid). Paced, the decoding thread waits until the inference thread's
current set is due to end, less one decode, and then decodes the newest set: one decode per
output, as fresh as before. Until both durations are known (the first sets), and whenever
the inference thread waits for input, it decodes at once, as before.
"""
from __future__ import annotations

import threading
import time

SMOOTHING = 0.25          # weight of the newest duration in the running means
MARGIN_S = 0.005          # decode this much earlier than the running means say


class DecodePacing:
    """Thread-safe: ``ready``/``taken`` from the inference thread, ``decoded`` and
    ``wait_until_due`` from the decoding thread; times are ``time.monotonic`` seconds."""

    def __init__(self, clock=time.monotonic):
        self._clock = clock
        self._condition = threading.Condition()
        self.busy_s: float | None = None     # inference thread: a set taken -> ready again
        self.decode_s: float | None = None   # decoding thread: one set
        self._taken_at: float | None = None
        self._measured = True                # this take's busy time is in busy_s
        self._decoded_since_take = False
        self._closed = False

    def ready(self) -> None:
        """The inference thread asks for its next set (it is done with the last one)."""
        with self._condition:
            if not self._measured:
                self.busy_s = _mean(self.busy_s, self._clock() - self._taken_at)
                self._measured = True

    def taken(self) -> None:
        """The inference thread got a decoded set: decoding for the one after may start when
        this one is due to end."""
        with self._condition:
            self._taken_at, self._measured = self._clock(), False
            self._decoded_since_take = False
            self._condition.notify_all()

    def decoded(self, seconds: float) -> None:
        """The decoding thread prepared a set in ``seconds``."""
        with self._condition:
            self.decode_s = _mean(self.decode_s, seconds)
            self._decoded_since_take = True

    def due(self) -> float | None:
        """When the next decode should start (None: now; inf: after the next take)."""
        with self._condition:
            return self._due()

    def _due(self) -> float | None:
        if self.busy_s is None or self.decode_s is None or self._taken_at is None:
            return None
        if self._decoded_since_take:       # one set waits already: the next take first
            return float("inf")
        return self._taken_at + self.busy_s - self.decode_s - MARGIN_S

    def wait_until_due(self, timeout: float) -> bool:
        """Wait (at most ``timeout`` s) until the next decode is due; True when it is."""
        with self._condition:
            deadline = self._clock() + timeout
            while not self._closed:
                due = self._due()
                now = self._clock()
                if due is None or due <= now:
                    return True
                if now >= deadline:
                    return False
                self._condition.wait(min(due, deadline) - now)
            return False

    def close(self) -> None:
        with self._condition:
            self._closed = True
            self._condition.notify_all()


def _mean(mean: float | None, value: float) -> float:
    return value if mean is None else (1 - SMOOTHING) * mean + SMOOTHING * value
