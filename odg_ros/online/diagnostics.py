"""Health of the online pipeline as plain dicts (the node packs them into diagnostic_msgs).

Tracks, over a sliding window of outputs: output rate, pipeline latency (node clock now -
image stamp, the diagnostic_msgs convention for a perception pipeline) p50/p95, and the
processing time per stage; and reports the skip/drop counters of the pipeline. Levels use
the diagnostic_msgs/DiagnosticStatus byte values.
"""
from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np

OK, WARN, ERROR, STALE = 0, 1, 2, 3

# Processing stages timed per set (seconds in, milliseconds out); lookup: the set's camera
# infos, poses and extrinsics, and its ego->image matrices.
STAGES = ("lookup", "decode_images", "upload", "model", "download", "publish")

# Counters that are normal under load and do not raise the level on their own.
LOAD_COUNTERS = ("stale_sets_dropped", "tf_ignored", "tf_received", "tf_frames_forgotten")
# Counters of inputs that arrived (not problems).
INPUT_COUNTERS = ("sets_completed", "tf_received")


class PipelineStats:
    """Thread-safe: outputs are recorded by the worker, status read by a timer."""

    def __init__(self, window: int = 100, rate_window_s: float = 5.0,
                 stale_after_s: float = 5.0, clock=time.monotonic,
                 max_tf_rate: float = float("inf")):
        self._lock = threading.Lock()
        self._clock = clock
        self._output_times: deque[float] = deque(maxlen=window)   # monotonic
        self._latencies: deque[float] = deque(maxlen=window)      # seconds
        self._stage_times: dict[str, deque[float]] = {s: deque(maxlen=window) for s in STAGES}
        self.rate_window_s = float(rate_window_s)
        self.stale_after_s = float(stale_after_s)
        self.outputs = 0
        self.max_tf_rate = float(max_tf_rate)
        self._previous_counters: dict[str, int] = {}
        self._started = clock()
        # (clock, counters) of the reports of the last stale_after_s: what happened meanwhile
        self._counter_history: deque[tuple[float, dict[str, int]]] = deque()
        self._window_base: dict[str, int] = {}

    def record_output(self, image_stamp: float, now: float, timings: dict[str, float]) -> None:
        """One published result: its image stamp and the node clock ``now`` (seconds)."""
        with self._lock:
            self.outputs += 1
            self._output_times.append(self._clock())
            self._latencies.append(now - image_stamp)
            for stage, seconds in timings.items():
                if stage in self._stage_times:
                    self._stage_times[stage].append(seconds)

    def rate_hz(self) -> float:
        with self._lock:
            return self._rate_locked(self._clock())

    def _rate_locked(self, now: float) -> float:
        recent = [t for t in self._output_times if now - t <= self.rate_window_s]
        if len(recent) < 2 or recent[-1] <= recent[0]:
            return 0.0
        return (len(recent) - 1) / (recent[-1] - recent[0])

    def snapshot(self) -> dict:
        """{'outputs', 'rate_hz', 'latency_ms': {'p50','p95'}, 'stage_ms': {stage: mean},
        'seconds_since_output'} (None where nothing was measured yet)."""
        with self._lock:
            now = self._clock()
            latencies = np.asarray(self._latencies, dtype=np.float64) * 1e3
            return {
                "outputs": self.outputs,
                "rate_hz": self._rate_locked(now),
                "latency_ms": {
                    "p50": float(np.percentile(latencies, 50)) if latencies.size else None,
                    "p95": float(np.percentile(latencies, 95)) if latencies.size else None,
                },
                "stage_ms": {s: (float(np.mean(v)) * 1e3 if v else None)
                             for s, v in self._stage_times.items()},
                "seconds_since_output": (now - self._output_times[-1]
                                         if self._output_times else None),
            }

    def status(self, counters: dict[str, int]) -> dict:
        """A DiagnosticStatus as a dict: {'level', 'message', 'values': [(key, str)]}.

        OK while sets flow and nothing was skipped since the last call; WARN when sets were
        skipped or dropped incomplete since the last call, before the first output, or when
        /tf brings more than ``max_tf_rate`` transforms/s; ERROR when no output came for
        ``stale_after_s`` (since the start or the last output) while inputs kept arriving,
        with the dominant reason they were dropped over that time.
        """
        snap = self.snapshot()
        now = self._clock()
        increased = {k: v - self._previous_counters.get(k, 0) for k, v in counters.items()
                     if v > self._previous_counters.get(k, 0)}
        elapsed = now - self._counter_history[-1][0] if self._counter_history else 0.0
        self._previous_counters = dict(counters)
        problems = {k: v for k, v in increased.items()
                    if k not in LOAD_COUNTERS and k not in INPUT_COUNTERS}
        problem_text = ", ".join(f"{k}: {v}" for k, v in sorted(problems.items()))

        # what happened over the last stale_after_s (the oldest report inside it as base)
        while self._counter_history and now - self._counter_history[0][0] > self.stale_after_s:
            self._window_base = self._counter_history.popleft()[1]
        self._counter_history.append((now, dict(counters)))
        base = self._window_base
        window = {k: v - base.get(k, 0) for k, v in counters.items() if v > base.get(k, 0)}
        arriving = any(k not in LOAD_COUNTERS for k in window)
        silent_for = (snap["seconds_since_output"] if snap["outputs"]
                      else now - self._started)
        tf_rate = increased.get("tf_received", 0) / elapsed if elapsed > 0 else 0.0

        if silent_for > self.stale_after_s and arriving:
            level = ERROR
            message = f"no output for {silent_for:.1f} s while inputs arrive"
            drops = {k: v for k, v in window.items()
                     if k not in LOAD_COUNTERS and k not in INPUT_COUNTERS}
            if drops:
                kind = max(drops, key=drops.get)
                total = sum(drops.values())
                message += (f": {100.0 * drops[kind] / total:.0f} % of dropped sets and "
                            f"inputs were {kind} ({drops[kind]} of {total})")
            elif window.get("sets_completed"):
                message += ": sets complete but inference gives no output (see the log)"
            else:
                message += ": no complete camera set"
        elif snap["outputs"] == 0:
            level = WARN
            message = "waiting for the first complete camera set"
            if problem_text:
                message += f" (skipped: {problem_text})"
        elif snap["seconds_since_output"] > self.stale_after_s:
            level = ERROR
            message = f"no output for {snap['seconds_since_output']:.1f} s"
            if problem_text:
                message += f" (skipped: {problem_text})"
        elif problems:
            level = WARN
            message = f"skipped or dropped input since last report: {problem_text}"
        else:
            level = OK
            message = f"running at {snap['rate_hz']:.1f} Hz"
        if tf_rate > self.max_tf_rate:
            level = max(level, WARN)
            message += (f"; /tf flood: {tf_rate:.0f} transforms/s (> {self.max_tf_rate:.0f}), "
                        f"{increased.get('tf_ignored', 0)} dropped unread as not needed")

        def fmt(value):
            return "n/a" if value is None else f"{value:.1f}"

        values = [("outputs", str(snap["outputs"])),
                  ("rate_hz", f"{snap['rate_hz']:.2f}"),
                  ("latency_p50_ms", fmt(snap["latency_ms"]["p50"])),
                  ("latency_p95_ms", fmt(snap["latency_ms"]["p95"]))]
        values += [(f"stage_{s}_ms", fmt(v)) for s, v in snap["stage_ms"].items()]
        values += [(k, str(v)) for k, v in sorted(counters.items())]
        return {"level": level, "message": message, "values": values}
