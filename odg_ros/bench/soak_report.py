"""``odg soak``'s figures: what a soak run recorded (odg_ros/ros/soak_run.py) summarised, checked
against the targets, drawn and written up; and the synthetic scenes it can loop.

Per run: resident memory over time and its growth after the warm-up; outputs, completed sets,
outputs per completed set, stale drops, inputs refused; latency percentiles: wall (the
reference image reaching the watcher -> its output reaching the watcher), the node's own
(~/debug/pipeline_latency_ms: its clock, the bag time, at publishing minus the stamp; over
the rate the replay achieved, as wall time; it reads low when the node's intake lags, as its
clock then does) and processing (set complete -> published, steady clock); every history reset, each explained by a new scene (the new scene's first
output restarts the history) or by two outputs of one scene further apart than the node's
history_max_gap (a node slower than that cannot keep a history), or else unexpected; the
longest output gap within a scene; the node's ERROR and WARN statuses.

Machine stalls: the soak samples the node's memory about once a second, so a gap of more than
``STALL_S`` between two samples means the soak's own process stood still too: the whole
machine stalled (memory pressure, a paused VM), not the node alone. ERROR reports from such a
stall until ``STALL_RECOVERY_S`` after it are the node reporting that fault (no output while
the machine stood still, then the backlog); they are counted apart from the others.

Scenes are told apart by the outputs' stamps: a stamp in another bag's time span, or one
earlier than the last (a loop starting over), begins a new scene.
"""
from __future__ import annotations

import bisect
from collections import Counter
from pathlib import Path

import numpy as np

ERROR = 2
WARN = 1
RESET_KINDS = ("history_resets_time_backwards", "history_resets_gap", "history_resets_teleport")
# stamps may lie this far outside their bag's log-time span (s)
SPAN_SLACK_S = 1.0
# the scenes of ``synthetic_scenes``: (traffic, roads)
SCENE_KINDS = (("normal", "city"), ("quiet", "open-road"), ("dense", "city"))
TARGET_RSS_GROWTH_MB = 20.0
# the percentile of resident memory that stands for its level over a stretch of time
UPPER_LEVEL = 90
TARGET_LATENCY_RATIO = 1.2
TARGET_RESTART_S = 10.0
# a gap between two memory samples (taken about once a second) longer than this: a stall of
# the machine; ERRORs until this long after it are the node's report of it (s)
STALL_S = 5.0
STALL_RECOVERY_S = 30.0


def percentiles(values, qs=(50, 90, 99)) -> dict[str, float | None]:
    values = np.asarray(list(values), dtype=np.float64)
    return {f"p{q}": (float(np.percentile(values, q)) if values.size else None) for q in qs}


def summarize(record: dict, warmup_s: float = 300.0) -> dict:
    """The figures of one run's record (see the module doc)."""
    wall = float(record.get("wall_s", 0.0))
    achieved = achieved_rate(record)
    rate = achieved if achieved is not None else record["rate"]
    scenes = output_scenes(record)
    latency = output_latencies(record)
    wall_latency = wall_latencies(record)
    last = record["diagnostics"][-1][3] if record["diagnostics"] else {}
    stalls = machine_stalls(record["rss"])
    summary = {
        "rate": record["rate"], "effective_rate": achieved, "wall_s": wall,
        "node_startup_s": record.get("node_startup_s"),
        "crashed": record.get("node_exit") is not None, "node_exit": record.get("node_exit"),
        "scenes_with_outputs": (scenes[-1] + 1) if scenes else 0,
        "outputs_received": len(record["outputs"]),
        "outputs": last.get("outputs"), "sets_completed": last.get("sets_completed"),
        "outputs_per_completed_set": (last["outputs"] / last["sets_completed"]
                                      if last.get("sets_completed") else None),
        "stale_sets_dropped": last.get("stale_sets_dropped"),
        "sets_waited": last.get("sets_waited"),
        "inputs_refused": {k: v for k, v in last.items() if k in _refusal_kinds() and v},
        "latency_ms_wall": percentiles(ms for _, ms in wall_latency if ms is not None),
        "outputs_without_their_image": sum(ms is None for _, ms in wall_latency),
        "node_latency_ms_bag": percentiles(ms for _, ms in latency),
        "node_latency_ms_as_wall": percentiles(ms / rate for _, ms in latency),
        "processing_ms": percentiles(ms for _, ms in record["processing_ms"]),
        "resets": _resets(record, scenes),
        "longest_output_gap": _longest_gap(record, scenes),
        "machine_stalls": stalls,
        "statuses": _statuses(record, stalls),
        "rss": _rss(record["rss"], wall, warmup_s),
    }
    summary["latency_drift"] = _latency_drift([(t, ms) for t, ms in wall_latency
                                               if ms is not None],
                                              summary["rss"]["warmup_s"])
    return summary


def _refusal_kinds() -> tuple[str, ...]:
    from ..online.errors import BAD_INPUT_KINDS
    return BAD_INPUT_KINDS


def _bag_of(record: dict, stamp: float) -> int:
    return next((i for i, b in enumerate(record["bags"])
                 if b["start"] - SPAN_SLACK_S <= stamp <= b["end"] + SPAN_SLACK_S), -1)


def output_scenes(record: dict) -> list[int]:
    """The scene (0, 1, ... in playing order) of each output."""
    scenes, scene, previous_bag, previous_stamp = [], -1, None, None
    for _, stamp, _ in record["outputs"]:
        bag = _bag_of(record, stamp)
        if previous_stamp is None or bag != previous_bag or stamp < previous_stamp:
            scene += 1
        scenes.append(scene)
        previous_bag, previous_stamp = bag, stamp
    return scenes


def achieved_rate(record: dict) -> float | None:
    """Bag seconds per wall second over the bags the replay finished (from its "playing"
    lines: each bag plays from one line to the next), or None with fewer than two lines."""
    announced = record.get("announced", [])
    spans = [b["end"] - b["start"] for b in record["bags"]]
    played = sum(spans[index - 1] for _, index, _ in announced[:-1])
    wall = announced[-1][0] - announced[0][0] if len(announced) > 1 else 0.0
    return played / wall if wall > 0 else None


def _paired(series: list, outputs: list, within: float = 0.5) -> list:
    """For each output, the value of ``series`` ((t, value) of the node's debug topics,
    published right after it) that arrived nearest to it, within ``within`` s (else None):
    a kill can lose one of the two messages, so they are paired by time, not by count."""
    times = [t for t, _ in series]
    out = []
    for t, *_ in outputs:
        i = bisect.bisect_left(times, t)
        near = min((j for j in (i - 1, i) if 0 <= j < len(times)),
                   key=lambda j: abs(times[j] - t), default=None)
        out.append(series[near][1] if near is not None and abs(times[near] - t) <= within
                   else None)
    return out


def wall_latencies(record: dict) -> list[tuple[float, float | None]]:
    """(arrival, wall ms from its reference image reaching the watcher) of each output, None
    where the image was not seen. A looping replay sends each stamp again: the image is its
    latest arrival at least the node's processing time (set complete -> published) before
    the output."""
    out = []
    for (t, _, since), processing in zip(record["outputs"],
                                         _paired(record["processing_ms"], record["outputs"])):
        fitting = [ms for ms in since if ms >= (processing or 0.0)]
        out.append((t, min(fitting) if fitting else None))
    return out


def output_latencies(record: dict) -> list[tuple[float, float]]:
    """(arrival, the node's pipeline latency in bag ms) of each output published in its own
    scene: one published after the bag time jumped to another scene (back, or into another
    bag) measures the jump, not the node."""
    out = []
    for (t, stamp, _), ms in zip(record["outputs"],
                                 _paired(record["latency_ms"], record["outputs"])):
        if ms is not None and ms >= 0 and \
                _bag_of(record, stamp + ms * 1e-3) == _bag_of(record, stamp):
            out.append((t, ms))
    return out


def _expected_resets(record: dict, scenes: list[int]) -> list[tuple[float, str]]:
    """(arrival, why) of each output that restarts the history: a new scene's first, or one
    further than history_max_gap after the previous output of its scene."""
    expected, gap = [], record.get("history_max_gap", 1.0)
    previous = None
    for (t, stamp, _), scene in zip(record["outputs"], scenes):
        if previous is not None and scene != previous[1]:
            expected.append((t, "scene"))
        elif previous is not None and stamp - previous[0] > gap:
            expected.append((t, "slow"))
        previous = (stamp, scene)
    return expected


def _resets(record: dict, scenes: list[int]) -> dict:
    """History resets from the node's counters, each matched to an output that explains it
    (within the diagnostics period, and a step later); those matched to none are
    unexpected."""
    diagnostics = record["diagnostics"]
    times = [d[0] for d in diagnostics]
    period = float(np.median(np.diff(times))) if len(times) > 2 else 1.0
    # the history restarts as a step begins; its output comes when the step is done
    step = max((ms for _, ms in record["processing_ms"]), default=0.0) * 1e-3
    expected = _expected_resets(record, scenes)
    matched = [False] * len(expected)
    unexpected, by_kind, previous_t, previous = [], Counter(), -np.inf, {}
    for t, _, _, counters in diagnostics:
        for kind in RESET_KINDS:
            increase = max(0, counters.get(kind, 0) - previous.get(kind, 0))
            by_kind[kind] += increase
            for _ in range(increase):
                i = next((i for i, (e, why) in enumerate(expected) if not matched[i] and
                          previous_t - period <= e <= t + period + step and
                          (why == "scene" or kind == "history_resets_gap")), None)
                if i is None:
                    unexpected.append({"t": t, "kind": kind.removeprefix("history_resets_")})
                else:
                    matched[i] = True
        previous, previous_t = counters, t
    return {"total": sum(by_kind.values()),
            "by_kind": {k.removeprefix("history_resets_"): v for k, v in by_kind.items()},
            "at_scene_changes": sum(m for m, (_, why) in zip(matched, expected)
                                    if why == "scene"),
            "outputs_further_apart_than_history_max_gap": sum(
                m for m, (_, why) in zip(matched, expected) if why == "slow"),
            "unexpected": unexpected,
            "new_scenes_without_reset": sum(not m for m, (_, why) in zip(matched, expected)
                                            if why == "scene")}


def _longest_gap(record: dict, scenes: list[int]) -> dict:
    """The longest wall time between two outputs of one scene."""
    best = {"seconds": None, "at_s": None}
    pairs = list(zip(record["outputs"], scenes))
    for ((a, *_), scene_a), ((b, *_), scene_b) in zip(pairs, pairs[1:]):
        if scene_a == scene_b and (best["seconds"] is None or b - a > best["seconds"]):
            best = {"seconds": b - a, "at_s": a}
    return best


def machine_stalls(samples) -> list[dict]:
    """Stretches in which the soak took no memory sample for over ``STALL_S``: its own
    process stood still, so the machine did (see the module doc)."""
    times = [t for t, _ in samples]
    return [{"at_s": a, "seconds": b - a} for a, b in zip(times, times[1:]) if b - a > STALL_S]


def _statuses(record: dict, stalls: list[dict]) -> dict:
    levels = Counter(level for _, level, _, _ in record["diagnostics"])
    errors = [(t, message) for t, level, message, _ in record["diagnostics"] if level >= ERROR]
    in_stall = [any(st["at_s"] <= t <= st["at_s"] + st["seconds"] + STALL_RECOVERY_S
                    for st in stalls) for t, _ in errors]
    warnings = Counter(message.split(":")[0][:60]
                       for _, level, message, _ in record["diagnostics"] if level == WARN)
    return {"reports": len(record["diagnostics"]), "ok": levels.get(0, 0),
            "warn": levels.get(WARN, 0), "error": len(errors),
            "error_in_machine_stalls": sum(in_stall),
            "errors": [{"t": t, "message": m, "in_machine_stall": stalled}
                       for (t, m), stalled in list(zip(errors, in_stall))[:10]],
            "warnings": dict(warnings.most_common(5))}


def _errors_outside_stalls(summary: dict) -> int:
    return summary["statuses"]["error"] - summary["statuses"]["error_in_machine_stalls"]


def _stall_note(summary: dict) -> str:
    stalls = summary["machine_stalls"]
    if not stalls:
        return ""
    longest = max(st["seconds"] for st in stalls)
    return (f" ({summary['statuses']['error_in_machine_stalls']} more during "
            f"{len(stalls)} machine stall{'s' * (len(stalls) > 1)}, the longest {longest:.0f} s, "
            "when the soak's own sampling stopped too)")


def _rss(samples, wall: float, warmup_s: float) -> dict:
    """Resident memory: first, peak, last (MB), and its growth after the warm-up (the first
    ``warmup_s``, at most half the run): the upper level (90th percentile) of the last minute
    (or tenth of the run) minus that of the steady part of the warm-up (its second half) and
    the minute after it; and the least-squares slope after the warm-up. The resident size
    swings between levels tens of MB apart, for seconds at a time, as the allocator hands
    large buffers back and takes them again: a median of a few seconds picks one level or the
    other by chance; the upper level is what the process holds."""
    if not samples:
        return {"samples": 0, "warmup_s": 0.0}
    t = np.array([s[0] for s in samples])
    mb = np.array([s[1] for s in samples]) / 2 ** 20
    warmup = min(warmup_s, wall / 2)
    window = min(60.0, max(wall / 10, 1.0))
    after = t >= warmup
    reference = mb[(t >= warmup / 2) & (t < warmup + window)]
    end = mb[t >= t[-1] - window]
    out = {"samples": len(samples), "warmup_s": warmup, "first_mb": float(mb[0]),
           "peak_mb": float(mb.max()), "last_mb": float(mb[-1])}
    if reference.size and end.size and after.sum() > 2:
        out["growth_after_warmup_mb"] = float(np.percentile(end, UPPER_LEVEL) -
                                              np.percentile(reference, UPPER_LEVEL))
        out["slope_mb_per_hour"] = float(np.polyfit(t[after], mb[after], 1)[0] * 3600)
    return out


def _latency_drift(latency, warmup: float) -> dict:
    """Median wall latency in the first and the second half after the warm-up: queueing
    would make the second grow."""
    pairs = [(t, ms) for t, ms in latency if t >= warmup]
    if len(pairs) < 4:
        return {}
    middle = (pairs[0][0] + pairs[-1][0]) / 2
    first = [ms for t, ms in pairs if t < middle]
    second = [ms for t, ms in pairs if t >= middle]
    return {"first_half_p50_ms": float(np.median(first)) if first else None,
            "second_half_p50_ms": float(np.median(second)) if second else None}


def summarize_restarts(record: dict) -> dict:
    """Each restart of a restart run (odg_ros/ros/soak_run.py restart_run): seconds from the new
    process's start to its first report and its first output; its outputs until the next
    kill, and those made of an image that reached the machine before the new process
    started (stale; unknown where the image was not seen), and its ERROR reports. A new
    process holds no history: every frame it uses came after its start."""
    outputs, reports = record["outputs"], record["diagnostics"]
    made_of = [None if ms is None else t - ms * 1e-3 for t, ms in wall_latencies(record)]
    cycles = record["restarts"]
    out = []
    for n, cycle in enumerate(cycles):
        end = cycles[n + 1]["killed_s"] if n + 1 < len(cycles) else float("inf")
        mine = [i for i in range(cycle["first_output_index"], len(outputs))
                if outputs[i][0] < end]
        images = [made_of[i] for i in mine]
        own = [r for r in reports[cycle["first_report_index"]:] if r[0] < end]
        out.append({"up_after_s": cycle["up_after_s"],
                    "first_output_after_s": cycle["first_output_after_s"],
                    "outputs": len(mine),
                    "stale_outputs": sum(t is not None and t < cycle["started_s"]
                                         for t in images),
                    "outputs_not_checked": sum(t is None for t in images),
                    "errors": sum(r[1] >= ERROR for r in own)})
    firsts = [c["first_output_after_s"] for c in out]
    return {"restarts": out, "first_output_after_s_max": max(firsts) if firsts else None,
            "first_output_after_s_median": float(np.median(firsts)) if firsts else None}


def verdicts(summaries: list[dict], long_enough_s: float = 600.0,
             restarts: dict | None = None) -> list[dict]:
    """Each target: what it asks, what was measured, met or not (None: not measured)."""
    out = []
    if restarts is not None and restarts["restarts"]:
        r = restarts["restarts"]
        out.append({"target": f"after a SIGKILL, the first output at most "
                              f"{TARGET_RESTART_S:g} s after the restart",
                    "measured": ", ".join(f"{c['first_output_after_s']:.1f} s" for c in r),
                    "met": restarts["first_output_after_s_max"] <= TARGET_RESTART_S})
        out.append({"target": "after a restart nothing stale is published, no ERROR",
                    "measured": f"{sum(c['stale_outputs'] for c in r)} stale outputs, "
                                f"{sum(c['errors'] for c in r)} ERROR reports",
                    "met": not any(c["stale_outputs"] or c["errors"] for c in r)})
    if summaries:
        out.append({"target": "no crash", "measured": ", ".join(
            f"{s['rate']:g}x: {'exit ' + str(s['node_exit']) if s['crashed'] else 'ran'}"
            for s in summaries), "met": not any(s["crashed"] for s in summaries)})
        out.append({"target": "no ERROR status (no fault was injected; a stall of the whole "
                              "machine is one)", "measured": ", ".join(
            f"{s['rate']:g}x: {_errors_outside_stalls(s)}" + _stall_note(s)
            for s in summaries),
            "met": all(_errors_outside_stalls(s) == 0 for s in summaries)})
        out.append({"target": "every history reset explained (a new scene, or outputs further "
                              "apart than history_max_gap)", "measured": "; ".join(
            f"{s['rate']:g}x: {s['resets']['at_scene_changes']} at new scenes, "
            f"{s['resets']['outputs_further_apart_than_history_max_gap']} after slow outputs, "
            f"{len(s['resets']['unexpected'])} unexplained" for s in summaries),
            "met": all(not s["resets"]["unexpected"] for s in summaries)})
    base = next((s for s in summaries if s["rate"] == 1.0), None)
    if base is not None:
        growth = base["rss"].get("growth_after_warmup_mb")
        long_enough = base["wall_s"] >= long_enough_s and base["rss"]["warmup_s"] >= 300
        out.append({"target": f"RSS grows at most {TARGET_RSS_GROWTH_MB:g} MB after the first "
                              "five minutes (1x)",
                    "measured": "n/a" if growth is None else
                    f"{growth:+.1f} MB over {(base['wall_s'] - base['rss']['warmup_s']) / 60:.1f}"
                    f" min after a {base['rss']['warmup_s'] / 60:.1f}-min warm-up",
                    "met": (growth <= TARGET_RSS_GROWTH_MB) if long_enough and
                    growth is not None else None})
        reference = base["latency_ms_wall"]["p50"]
        for s in summaries:
            if s is base or reference is None or s["latency_ms_wall"]["p50"] is None:
                continue
            ratio = s["latency_ms_wall"]["p50"] / reference
            out.append({"target": f"median latency at {s['rate']:g}x within "
                                  f"{TARGET_LATENCY_RATIO:g}x of 1x",
                        "measured": f"{s['latency_ms_wall']['p50']:.0f} ms against "
                                    f"{reference:.0f} ms: {ratio:.2f}x",
                        "met": ratio <= TARGET_LATENCY_RATIO})
    return out


def plot_soak(records: list[dict], path: Path) -> Path:
    """Resident memory and wall latency over time, one colour per run."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    for record in records:
        label = f"{record['rate']:g}x"
        if record["rss"]:
            top.plot([t / 60 for t, _ in record["rss"]],
                     [b / 2 ** 20 for _, b in record["rss"]], label=label)
        points = [(t / 60, ms) for t, ms in wall_latencies(record) if ms is not None]
        if points:
            bottom.plot(*zip(*points), ".", markersize=2, label=label)
    top.set_ylabel("odg_node resident memory (MB)")
    top.set_title("soak: the node's memory, and the latency of each output")
    bottom.set_ylabel("pipeline latency, wall (ms)")
    bottom.set_xlabel("minutes since the replay started")
    for axis in (top, bottom):
        axis.grid(alpha=0.3)
        if axis.has_data():
            axis.legend(loc="upper right")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def synthetic_scenes(folder: Path, seconds: float = 20.0, image_hw=None,
                     kinds=SCENE_KINDS, progress: bool = True) -> list[Path]:
    """One synthetic scene of each kind (traffic, roads), bagged with ``odg bag``, in
    ``folder`` (reused when already there): the bags, in order."""
    from ..bags.nuscenes_source import NuScenesSensorTables
    from ..bags.writer import write_scene_bag
    from ..data.synth.city.scene import SceneKind
    from ..data.synth.generate import DEFAULT_IMAGE_HW, generate

    folder = Path(folder)
    image_hw = tuple(image_hw or DEFAULT_IMAGE_HW)
    bags = []
    for seed, (traffic, roads) in enumerate(kinds):
        name = f"{roads}_{traffic}_{seconds:g}s_{image_hw[0]}x{image_hw[1]}"
        bag = folder / "bags" / name
        if not (bag / "metadata.yaml").is_file():
            world = folder / "worlds" / name
            if not (world / "v1.0-trainval").is_dir():
                generate(str(world), scenes=1, seconds=seconds, seed=seed, image_hw=image_hw,
                         progress=progress, kind=SceneKind(traffic, roads))
            tables = NuScenesSensorTables(world)
            # no LiDAR: the node does not read it (the replay would skip it anyway)
            write_scene_bag(tables.scene_records(tables.scene_names()[0], with_lidar=False),
                            bag, force=bag.exists(), progress=progress)
        bags.append(bag)
    return bags
