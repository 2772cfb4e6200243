"""The demo's numbers (defined in the package docstring): keyframe scores, rates, drops and
latencies of one session, as a summary, its text and its JSON."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import REFERENCE_CAMERA, DemoError
from .records import CameraSets, SessionRecord


def keyframes_by_stamp(infos: list[dict]) -> dict[int, int]:
    """CAM_FRONT stamp (ns) -> index into ``infos`` of every keyframe that has GT."""
    return {int(info["cams"][REFERENCE_CAMERA]["timestamp"]) * 1000: i
            for i, info in enumerate(infos) if info["occ_path"]}


def score_keyframes(meta: dict, grids: dict[int, np.ndarray], progress: bool = True):
    """Score the received grids of keyframes against the Occ3D GT.

    meta: the infos dict (``metrics.score.load_scoring_infos``); grids: stamp_ns -> uint8 [X, Y, Z].
    Returns (OccScore.result() or None when no keyframe grid arrived, scored info indices,
    per-keyframe mIoU {info index: percent or None}).
    """
    from ..data.occ_io import load_occ
    from ..metrics.rayiou import LidarOrigins
    from ..metrics.score import OccScore, resolve_occ_root

    infos, dataset = meta["infos"], meta["dataset"]
    root = resolve_occ_root(meta)
    by_stamp = keyframes_by_stamp(infos)
    scored = sorted(by_stamp[s] for s in grids if s in by_stamp)
    if not scored:
        return None, [], {}
    stamp_of = {i: s for s, i in by_stamp.items()}
    origins = LidarOrigins(infos)
    total = OccScore(dataset)
    single = {}
    for i in tqdm(scored, desc="scoring keyframes", unit="keyframe", disable=not progress):
        gt, _, mask_camera = load_occ(root / infos[i]["occ_path"], dataset)
        pred = grids[stamp_of[i]]
        if pred.shape != gt.shape:
            raise DemoError(f"received grid {pred.shape} does not match the GT {gt.shape}")
        total.add(pred, gt, mask_camera, origins(i))
        one = OccScore(dataset, rayiou=False)
        one.add(pred, gt, mask_camera)
        single[i] = one.result()["mIoU"]
    return total.result(), scored, single


def _percentile(values, q) -> float | None:
    values = np.asarray(values, dtype=np.float64)
    return float(np.percentile(values, q)) if values.size else None


def grid_latencies_ms(record: SessionRecord, sets: CameraSets) -> np.ndarray:
    """Wall-clock latency of every received grid whose set's completion was seen on /clock
    (see the module docstring), milliseconds."""
    index = {int(s): i for i, s in enumerate(sets.reference_ns)}
    out = []
    for grid in record.grids:
        i = index.get(grid.stamp_ns)
        if i is None or sets.complete_ns[i] < 0:
            continue
        published = record.clock_wall.get(int(sets.complete_ns[i]))
        if published is not None:
            out.append((grid.wall_s - published) * 1e3)
    return np.asarray(out, dtype=np.float64)


DROP_COUNTERS = ("stale_sets_dropped", "dropped_incomplete_sets")


def summarize_session(record: SessionRecord, sets: CameraSets, meta: dict, score: dict | None,
                      scored: list[int], rate: float) -> dict:
    """The demo's numbers (see the package docstring), JSON-ready (None where unmeasured)."""
    from ..online.errors import BAD_INPUT_KINDS

    diag = record.diagnostics
    reasons = {k: _counter(diag, k) for k in DROP_COUNTERS + BAD_INPUT_KINDS}
    dropped = sum(reasons.values())
    frames_in = sets.num_complete
    frames_out = len(record.grids)
    node = node_numbers(record)
    step_ms = sum(node["stage_ms"].values())
    latencies = grid_latencies_ms(record, sets)
    fps, input_fps = output_and_input_fps(record, sets)
    node_outputs = _counter(diag, "outputs")
    return {
        "frames_in": frames_in,
        "frames_out": frames_out,
        "dropped": dropped,
        "fps": fps,
        "latency_ms_p50": _percentile(latencies, 50),
        "latency_ms_p95": _percentile(latencies, 95),
        **score_numbers(score),
        "keyframes": len(keyframes_by_stamp(meta["infos"])),
        "keyframes_scored": len(scored),
        "dropped_by_reason": {k: v for k, v in reasons.items() if v},
        # outputs the node published that never reached the planner (reliable, keep-last 1)
        "lost_in_transport": max(0, node_outputs - frames_out) if diag else None,
        # sets published but neither output nor counted by the node (every image of the set
        # lost on the way: best effort); 0 normally
        "unaccounted": (frames_in - frames_out - dropped - max(0, node_outputs - frames_out)
                        if diag else None),
        "input_fps": input_fps,
        "node_capacity_fps": 1e3 / step_ms if step_ms > 0 else None,
        "rate": rate,
        "latency_ms_mean": float(latencies.mean()) if latencies.size else None,
        "latency_samples": int(latencies.size),
        "objects_per_output": (float(np.mean([n for _, n in record.objects]))
                               if record.objects else None),
        "node": node,
        "warnings": list(record.warnings),
    }


def _counter(diag: dict, key: str) -> int:
    try:
        return int(diag.get(key, "0"))
    except ValueError:
        return 0


def output_and_input_fps(record: SessionRecord, sets: CameraSets):
    """Grids received per wall second (first to last grid), and sets published per second."""
    wall = [g.wall_s for g in record.grids]
    fps = (len(wall) - 1) / (wall[-1] - wall[0]) if len(wall) >= 2 and wall[-1] > wall[0] \
        else None
    published = [record.clock_wall[int(c)] for c in sets.complete_ns
                 if c >= 0 and int(c) in record.clock_wall]
    input_fps = ((len(published) - 1) / (published[-1] - published[0])
                 if len(published) >= 2 and published[-1] > published[0] else None)
    return fps, input_fps


def score_numbers(score: dict | None) -> dict:
    """mIoU, RayIoU (and at 1, 2, 4 m), geometry IoU and per class; None without a score."""
    score = score or {}
    return {"mIoU": score.get("mIoU"), "RayIoU": score.get("RayIoU"),
            "RayIoU@1": score.get("RayIoU@1"), "RayIoU@2": score.get("RayIoU@2"),
            "RayIoU@4": score.get("RayIoU@4"), "IoU_geometry": score.get("IoU_geometry"),
            "per_class": score.get("per_class", {})}


def node_numbers(record: SessionRecord) -> dict:
    """What the node said of itself: its outputs, ~/fps, stage times, latency on its clock,
    every other counter of its final diagnostics, and its status message."""
    diag = record.diagnostics
    stage_ms = {}
    for key, value in diag.items():
        if key.startswith("stage_") and key.endswith("_ms"):
            try:
                stage_ms[key[len("stage_"):-len("_ms")]] = float(value)
            except ValueError:
                pass       # "n/a" before the first output

    def node_float(key):
        try:
            return float(diag[key])
        except (KeyError, ValueError):
            return None

    return {
        "outputs": _counter(diag, "outputs") if diag else None,
        "fps_topic_median": (float(np.median([f for f in record.fps_samples if f > 0]))
                             if any(f > 0 for f in record.fps_samples) else None),
        "stage_ms": stage_ms,
        "latency_sim_ms": {"p50": node_float("stamp_age_p50_ms (node clock)"),
                           "p95": node_float("stamp_age_p95_ms (node clock)")},
        "receipt_to_publish_ms": {"p50": node_float("receipt_to_publish_p50_ms (steady)"),
                                  "p95": node_float("receipt_to_publish_p95_ms (steady)")},
        "counters": {k: v for k, v in diag.items()
                     if k != "rate_hz" and "_ms (" not in k and ": " not in k
                     and not k.startswith("stage_")},
        "status": record.diagnostics_message,
    }


def format_value(value, spec=".2f", none="-") -> str:
    return none if value is None or (isinstance(value, float) and math.isnan(value)) \
        else format(value, spec)


def format_summary(report: dict) -> str:
    """The demo's table (the numbers of ``summarize`` plus the run's settings and times)."""
    r = report
    reasons = r["dropped_by_reason"]
    why = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in reasons.items()) or "none"
    world = r.get("world", {})
    rows = [
        ("camera sets in", f"{r['frames_in']}",
         f"published by the replay at {r['rate']:g} x real time "
         f"({format_value(r['input_fps'], '.1f')} sets/s)"),
        ("grids out", f"{r['frames_out']}", "received by the planner stand-in"
         + (f", {r['lost_in_transport']} lost in transport" if r.get("lost_in_transport")
            else "")),
        ("dropped", f"{r['dropped']}", why),
        ("FPS", format_value(r["fps"]), f"grids per wall second; node capacity "
         f"{format_value(r['node_capacity_fps'], '.1f')}/s from its stage times"),
        ("latency p50 / p95", f"{format_value(r['latency_ms_p50'], '.0f')} / "
         f"{format_value(r['latency_ms_p95'], '.0f')} ms", "set complete -> grid at the planner"),
        ("keyframes scored", f"{r['keyframes_scored']} of {r['keyframes']}",
         "the others were dropped by the node"
         if r["keyframes_scored"] < r["keyframes"] else ""),
        ("mIoU", format_value(r["mIoU"]), "camera mask, 17 classes"),
        ("RayIoU", format_value(r["RayIoU"]), f"@1/2/4 m: {format_value(r['RayIoU@1'])} / "
         f"{format_value(r['RayIoU@2'])} / {format_value(r['RayIoU@4'])}"),
    ]
    width = max(len(a) for a, _, _ in rows)
    value_width = max(len(b) for _, b, _ in rows)
    title = "odg demo"
    if world:
        title += (f": 1 synthetic scene, {world['seconds']:g} s, seed {world['seed']}; "
                  f"checkpoint {r.get('checkpoint', '?')}")
    lines = [title, "-" * max(60, len(title))]
    lines += [f"{a:<{width}}  {b:>{value_width}}  {c}".rstrip() for a, b, c in rows]
    lines.append("-" * max(60, len(title)))
    t = r.get("timings_s", {})
    if t:
        lines.append("wall time: " + ", ".join(f"{k.replace('_', ' ')} {v:.0f} s"
                                               for k, v in t.items()))
    for warning in r.get("warnings", []):
        lines.append(f"warning: {warning}")
    return "\n".join(lines)


def write_json(report: dict, path) -> None:
    Path(path).write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")
