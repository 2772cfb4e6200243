"""Health of the online pipeline as plain dicts (the node packs them into diagnostic_msgs).

Tracks, over a sliding window of outputs: output rate, two latencies p50/p95 and the
processing time per stage; reports the skip/drop counters of the pipeline and, per input
topic, the messages received and the seconds since the last one. Levels use the
diagnostic_msgs/DiagnosticStatus byte values.

Two clocks, named in every value: rates, stage times, "receipt_to_publish" (the set's last
image received -> its results published) and "no input for N s" run on the steady clock
(``time.monotonic``), so they stay true under simulated time, a paused bag or a clock jump;
"stamp_age" is the node's clock at publication minus the image stamp (the age of the data in
the clock that stamped it: sim time while a bag is replayed with use_sim_time).
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

# Counters that are normal under load and do not raise the level on their own (sets_waited:
# sets that waited for their poses / extrinsics; sets_waiting: how many wait now).
LOAD_COUNTERS = ("stale_sets_dropped", "tf_ignored", "tf_received", "tf_frames_forgotten",
                 "sets_waited", "sets_waiting")
# Counters of inputs that arrived (not problems).
INPUT_COUNTERS = ("sets_completed", "tf_received")


def transform_topics_needed(pose_source: str, extrinsics_source: str) -> tuple[bool, bool]:
    """(whether /tf is needed, whether one of /tf and /tf_static is) for "never received":
    /tf carries the ego pose (pose_source tf); camera transforms may come on either
    (extrinsics_source tf) or not at all (auto: the rig file then). /tf_static on its own is
    never needed."""
    return pose_source == "tf", pose_source != "tf" and extrinsics_source == "tf"


class InputMonitor:
    """Per input topic: messages received and the steady time of the last one. Thread-safe:
    the subscription callbacks record, a timer reads.

    Every topic is reported; ``never_received`` names only those the configuration needs
    (``watch(topic, needed=False)``: an optional one, e.g. /tf_static when transforms can
    come from /tf) and, for topics of which one is enough (``need_one_of``), the group."""

    def __init__(self, topics=(), clock=time.monotonic):
        self._clock = clock
        self._lock = threading.Lock()
        self._counts = {topic: 0 for topic in topics}
        self._needed = set(self._counts)
        self._groups: list[tuple[str, ...]] = []
        self._last: dict[str, float] = {}

    def watch(self, topic: str, needed: bool = True) -> None:
        """Report ``topic`` from now on, as never received until it is."""
        with self._lock:
            self._counts.setdefault(topic, 0)
            if needed:
                self._needed.add(topic)
            else:
                self._needed.discard(topic)

    def need_one_of(self, topics) -> None:
        """At least one of ``topics`` (watched) is needed, e.g. camera transforms on /tf or
        /tf_static."""
        with self._lock:
            self._groups.append(tuple(topics))

    def never_received(self) -> list[str]:
        """The needed topics (and groups: 'a or b') of which no message came."""
        with self._lock:
            never = [t for t, n in self._counts.items() if n == 0 and t in self._needed]
            never += [" or ".join(group) for group in self._groups
                      if not any(self._counts.get(t, 0) for t in group)]
            return never

    def received(self, topic: str) -> None:
        now = self._clock()
        with self._lock:
            self._counts[topic] = self._counts.get(topic, 0) + 1
            self._last[topic] = now

    def snapshot(self) -> dict[str, tuple[int, float | None]]:
        """topic -> (messages received, seconds since the last one or None)."""
        now = self._clock()
        with self._lock:
            return {t: (n, now - self._last[t] if t in self._last else None)
                    for t, n in self._counts.items()}


class PipelineStats:
    """Thread-safe: outputs are recorded by the worker, status read by a timer. ``inputs``:
    the InputMonitor of the node's subscriptions (None: inputs judged by the counters);
    ``first_set_grace_s``: how long the first complete set may wait for its poses before it
    counts as silent (the pipeline's pose_wait)."""

    def __init__(self, window: int = 100, rate_window_s: float = 5.0,
                 stale_after_s: float = 5.0, clock=time.monotonic,
                 max_tf_rate: float = float("inf"), inputs: InputMonitor | None = None,
                 first_set_grace_s: float = 0.0):
        self._lock = threading.Lock()
        self._clock = clock
        self.inputs = inputs
        self._output_times: deque[float] = deque(maxlen=window)   # steady
        self._ages: deque[float] = deque(maxlen=window)           # s, node clock
        self._latencies: deque[float] = deque(maxlen=window)      # s, steady
        self._stage_times: dict[str, deque[float]] = {s: deque(maxlen=window) for s in STAGES}
        self._refined: deque[float] = deque(maxlen=window)       # query budget: share refined
        self._last_budget: str | None = None
        self.rate_window_s = float(rate_window_s)
        self.stale_after_s = float(stale_after_s)
        self.outputs = 0
        self.max_tf_rate = float(max_tf_rate)
        self._previous_counters: dict[str, int] = {}
        self._first_set: float | None = None       # steady time the first set completed
        self.first_set_grace_s = float(first_set_grace_s)
        # (clock, counters) of the reports of the last stale_after_s: what happened meanwhile
        self._counter_history: deque[tuple[float, dict[str, int]]] = deque()
        self._window_base: dict[str, int] = {}

    def record_complete_set(self) -> None:
        """A camera set became complete (the no-output timer starts at the first one)."""
        if self._first_set is None:
            with self._lock:
                if self._first_set is None:
                    self._first_set = self._clock()

    def record_output(self, image_stamp: float, now: float, timings: dict[str, float],
                      received: float | None = None, query_budget: str | None = None,
                      refined_fraction: float | None = None) -> None:
        """One published result: its image stamp and the node clock ``now`` (seconds), the
        steady time its set's last image was received (None: unknown), and the query budget
        it ran with the share of the queries refined (None: not reported)."""
        published = self._clock()
        with self._lock:
            self.outputs += 1
            self._output_times.append(published)
            self._ages.append(now - image_stamp)
            if received is not None:
                self._latencies.append(published - received)
            for stage, seconds in timings.items():
                if stage in self._stage_times:
                    self._stage_times[stage].append(seconds)
            if query_budget is not None:
                self._last_budget = query_budget
            if refined_fraction is not None:
                self._refined.append(float(refined_fraction))

    def rate_hz(self) -> float:
        with self._lock:
            return self._rate_locked(self._clock())

    def _rate_locked(self, now: float) -> float:
        recent = [t for t in self._output_times if now - t <= self.rate_window_s]
        if len(recent) < 2 or recent[-1] <= recent[0]:
            return 0.0
        return (len(recent) - 1) / (recent[-1] - recent[0])

    def snapshot(self) -> dict:
        """{'outputs', 'rate_hz', 'receipt_to_publish_ms' (steady) and 'stamp_age_ms' (node
        clock): {'p50','p95'}, 'stage_ms': {stage: mean}, 'seconds_since_output',
        'query_budget' (the last output's), 'refined_fraction' (mean)} (None where nothing
        was measured yet)."""
        def percentiles(values):
            ms = np.asarray(values, dtype=np.float64) * 1e3
            return {q: float(np.percentile(ms, n)) if ms.size else None
                    for q, n in (("p50", 50), ("p95", 95))}

        with self._lock:
            now = self._clock()
            return {
                "outputs": self.outputs,
                "rate_hz": self._rate_locked(now),
                "receipt_to_publish_ms": percentiles(self._latencies),
                "stamp_age_ms": percentiles(self._ages),
                "stage_ms": {s: (float(np.mean(v)) * 1e3 if v else None)
                             for s, v in self._stage_times.items()},
                "seconds_since_output": (now - self._output_times[-1]
                                         if self._output_times else None),
                "query_budget": self._last_budget,
                "refined_fraction": float(np.mean(self._refined)) if self._refined else None,
            }

    def status(self, counters: dict[str, int], extrinsics: dict[str, str] | None = None) \
            -> dict:
        """A DiagnosticStatus as a dict: {'level', 'message', 'values': [(key, str)]}.

        OK while sets flow and nothing was skipped since the last call; WARN when sets were
        skipped or dropped incomplete since the last call, before the first output, when no
        input came for ``stale_after_s`` ("no input for N s": a stopped bag, a dead driver),
        or when /tf brings more than ``max_tf_rate`` transforms/s; ERROR when no output came
        for ``stale_after_s`` (since the last output, or the first complete camera set plus
        the wait it may spend on its poses, ``first_set_grace_s``) while inputs kept
        arriving, with the dominant reason they were dropped over that time: never before
        the first complete set (a node waiting for its cameras is not failing; its WARN
        names what it waits for). The needed topics that never sent are named in
        every non-OK message. ``extrinsics``: camera -> where its extrinsics come from
        (reported as values).
        """
        snap = self.snapshot()
        now = self._clock()
        increased = {k: v - self._previous_counters.get(k, 0) for k, v in counters.items()
                     if v > self._previous_counters.get(k, 0)}
        elapsed = now - self._counter_history[-1][0] if self._counter_history else 0.0
        self._previous_counters = dict(counters)
        problems = {k: v for k, v in increased.items()
                    if k not in LOAD_COUNTERS and k not in INPUT_COUNTERS}

        # what happened over the last stale_after_s (the oldest report inside it as base)
        while self._counter_history and now - self._counter_history[0][0] > self.stale_after_s:
            self._window_base = self._counter_history.popleft()[1]
        self._counter_history.append((now, dict(counters)))
        base = self._window_base
        window = {k: v - base.get(k, 0) for k, v in counters.items() if v > base.get(k, 0)}
        inputs = self.inputs.snapshot() if self.inputs is not None else {}
        ages = [age for _, age in inputs.values() if age is not None]
        quiet_for = min(ages) if ages else None           # since the last input, any topic
        if inputs:
            arriving = quiet_for is not None and quiet_for <= self.stale_after_s
        else:
            arriving = any(k not in LOAD_COUNTERS for k in window)
        level, message = self._verdict(snap, now, problems, window, arriving, quiet_for)
        never = self.inputs.never_received() if self.inputs is not None else []
        if never and level != OK:
            message += f"; never received: {', '.join(never)}"
        tf_rate = increased.get("tf_received", 0) / elapsed if elapsed > 0 else 0.0
        if tf_rate > self.max_tf_rate:
            level = max(level, WARN)
            message += (f"; /tf flood: {tf_rate:.0f} transforms/s (> {self.max_tf_rate:.0f}), "
                        f"{increased.get('tf_ignored', 0)} dropped unread as not needed")
        values = self._values(snap, counters, inputs)
        values += [(f"extrinsics {camera}", source)
                   for camera, source in (extrinsics or {}).items()]
        return {"level": level, "message": message, "values": values}

    def _verdict(self, snap, now, problems, window, arriving, quiet_for) -> tuple[int, str]:
        """(level, message) of ``status`` before the input and /tf notes."""
        problem_text = ", ".join(f"{k}: {v}" for k, v in sorted(problems.items()))
        skipped = f" (skipped: {problem_text})" if problem_text else ""
        with self._lock:
            first_set = self._first_set
        silent_for = (snap["seconds_since_output"] if snap["outputs"] else None
                      if first_set is None else now - first_set - self.first_set_grace_s)
        if silent_for is not None and silent_for > self.stale_after_s and arriving:
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
            return ERROR, message
        if quiet_for is not None and quiet_for > self.stale_after_s:
            return WARN, f"no input for {quiet_for:.1f} s" + (
                f" (last output {snap['seconds_since_output']:.1f} s ago)"
                if snap["outputs"] else "")
        if snap["outputs"] == 0 and first_set is None:
            return WARN, "waiting for the first complete camera set" + skipped
        if snap["outputs"] == 0:
            return WARN, (f"waiting for the first output (the first set completed "
                          f"{now - first_set:.1f} s ago)" + skipped)
        if snap["seconds_since_output"] > self.stale_after_s:
            return ERROR, f"no output for {snap['seconds_since_output']:.1f} s" + skipped
        if problems:
            return WARN, f"skipped or dropped input since last report: {problem_text}"
        return OK, f"running at {snap['rate_hz']:.1f} Hz"

    @staticmethod
    def _values(snap, counters, inputs) -> list[tuple[str, str]]:
        def fmt(value):
            return "n/a" if value is None else f"{value:.1f}"

        values = [("outputs", str(snap["outputs"])),
                  ("rate_hz", f"{snap['rate_hz']:.2f}")]
        for name, clock in (("receipt_to_publish", "steady"), ("stamp_age", "node clock")):
            for q in ("p50", "p95"):
                values.append((f"{name}_{q}_ms ({clock})", fmt(snap[f"{name}_ms"][q])))
        values += [(f"stage_{s}_ms", fmt(v)) for s, v in snap["stage_ms"].items()]
        values += [("query_budget (last output)", snap["query_budget"] or "n/a"),
                   ("queries_refined_percent (mean)",
                    fmt(None if snap["refined_fraction"] is None
                        else 100 * snap["refined_fraction"]))]
        for topic, (count, age) in inputs.items():
            values += [(f"{topic}: received", str(count)),
                       (f"{topic}: seconds since last", fmt(age))]
        values += [(k, str(v)) for k, v in sorted(counters.items())]
        return values
