"""What the padding and the visibility cost of the node's step, measured two ways side by side.

1. **marks**: the step's own marks (online/marks.py) recorded in CPU time, on steps of a
   predictor at the node's settings: each stage's CPU time over its step's;
2. **difference**: the same step without the stage (no padding; no visibility), set by set
   interleaved with the full step: the CPU time it saves over the full step's.

Every variant steps over the same camera sets in one run, taking turns set by set (the order
rotated each set, so none always follows the same one), at ``threads`` torch threads (one
by default: what other processes on the machine inflate least). A share is the median of
the per-set ratios. CPU time is the calling thread's on one thread (``time.thread_time``:
the whole step runs there, and a thread left over from earlier work, such as an OpenMP
worker still spinning after a parallel region, is not counted), else the process's
(``time.process_time``, torch's threads included). Its kernel part (page faults of the
step's fresh buffers, a worker's ``sched_yield``) is reported apart, per step: where it
grows it inflates the differences more than the marks.

``tools/node_rate.py``, ``tools/visibility_agreement.py --step-share`` and ``odg bench
--shares`` all report these numbers.
"""
from __future__ import annotations

import resource
import statistics
import time

import torch
from tqdm import tqdm

from ..model_config import ModelConfig
from ..online.marks import STEP_STAGES, MarkRecorder
from .step_timing import node_predictor, node_settings

# the stages that can be switched off, so measured both ways
SHARED_STAGES = ("padding", "visibility")
# marks and difference further apart than this (share of the step) get a note
AGREEMENT = 0.03


def without(stage: str, model, cfg: ModelConfig, settings: dict):
    """The node's predictor without ``stage`` (one of SHARED_STAGES)."""
    if stage == "padding":
        return node_predictor(model, cfg.replace(occupancy_padding=False), "cpu", settings)
    if stage == "visibility":
        return node_predictor(model, cfg, "cpu", {**settings, "visibility": False})
    raise ValueError(f"stage {stage!r}: expected one of {SHARED_STAGES}")


def _clocks(threads: int):
    """(CPU clock, kernel-time clock) in seconds: the calling thread's on one thread (where
    the platform has per-thread usage), else the process's."""
    who = getattr(resource, "RUSAGE_THREAD", None) if threads == 1 else None
    if who is None:
        return time.process_time, lambda: resource.getrusage(resource.RUSAGE_SELF).ru_stime
    return time.thread_time, lambda: resource.getrusage(who).ru_stime


@torch.inference_mode()
def stage_shares(model, cfg: ModelConfig, sets, settings: dict | None = None,
                 stages=SHARED_STAGES, threads: int = 1, warmup: int = 2,
                 progress: bool = True) -> dict:
    """The shares of ``stages`` in the node's CPU step, by marks and by difference (module
    docstring), over camera ``sets`` (each the arguments of ``OnlinePredictor.step``, in
    order: the first ``warmup`` untimed); ``settings``: the node's (``node_settings``)."""
    settings = settings or node_settings()
    if "padding" in stages and not cfg.occupancy_padding:
        raise ValueError(f"{cfg.name} does not pad its grid: no padding to measure")
    if "visibility" in stages and not settings["visibility"]:
        raise ValueError("visibility off in the settings: no visibility to measure")
    if len(sets) <= warmup:
        raise ValueError(f"{len(sets)} sets: more than the {warmup} warm-up ones needed")
    threads_before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        predictors = {"full": node_predictor(model, cfg, "cpu", settings),
                      "marked": node_predictor(model, cfg, "cpu", settings)}
        if predictors["marked"].mode != "eager":
            raise ValueError(f"compile {settings['compile']} runs a {predictors['marked'].mode}"
                             " step on this CPU: it has no marks (the shares need an eager step)")
        predictors.update({f"without {s}": without(s, model, cfg, settings) for s in stages})
        clock, system_clock = _clocks(threads)
        recorder = MarkRecorder("cpu", clock=clock)
        cpu = {name: [] for name in predictors}
        system = {name: [] for name in predictors}
        names = list(predictors)
        for i in tqdm(range(len(sets)), desc="step shares", disable=not progress):
            turn = i % len(names)
            for name in names[turn:] + names[:turn]:
                start, start_system = clock(), system_clock()
                if name == "marked":
                    with recorder:
                        predictors[name].step(*sets[i])
                else:
                    predictors[name].step(*sets[i])
                if i >= warmup:
                    cpu[name].append(1e3 * (clock() - start))
                    system[name].append(1e3 * (system_clock() - start_system))
            if i < warmup:
                recorder.times.clear()
    finally:
        torch.set_num_threads(threads_before)
    marks = recorder.times                        # one entry per timed step of "marked"

    def median_ratio(parts, wholes):
        return round(statistics.median(p / w for p, w in zip(parts, wholes)), 4)
    by_marks = {s: median_ratio(marks[s], cpu["marked"]) for s in stages}
    by_difference = {s: median_ratio([f - w for f, w in zip(cpu["full"], cpu[f"without {s}"])],
                                     cpu["full"]) for s in stages}
    first = predictors["full"]
    return {"threads": threads, "precision": first.precision, "mode": first.mode,
            "sets": len(cpu["full"]), "warmup": warmup,
            "step_cpu_ms": round(statistics.median(cpu["full"]), 1),
            "marked_step_cpu_ms": round(statistics.median(cpu["marked"]), 1),
            "stage_cpu_ms": {k: round(statistics.median(marks[k]), 2)
                             for k in STEP_STAGES if k in marks},
            "without_cpu_ms": {s: round(statistics.median(cpu[f"without {s}"]), 1)
                               for s in stages},
            "system_ms": {name: round(statistics.median(v), 1) for name, v in system.items()},
            "by_marks": by_marks, "by_difference": by_difference,
            "together_by_marks": round(sum(by_marks.values()), 4),
            "agree": all(abs(by_marks[s] - by_difference[s]) <= AGREEMENT for s in stages)}


def format_shares(result: dict) -> str:
    """One paragraph of ``stage_shares``' result."""
    r = result
    head = (f"shares of the step's {r['step_cpu_ms']:.0f} ms of CPU ({r['precision']}, "
            f"{r['mode']}, {r['threads']} thread{'s' if r['threads'] > 1 else ''}, median of "
            f"{r['sets']} sets): ")
    parts = [f"{s} {100 * r['by_marks'][s]:.1f} % by its marks, "
             f"{100 * r['by_difference'][s]:.1f} % by the step without it"
             for s in r["by_marks"]]
    line = head + "; ".join(parts)
    kernel = r["system_ms"]["full"]
    line += f"; kernel time {kernel:.0f} ms a step"
    if not r["agree"]:
        line += (f" (marks and differences more than {100 * AGREEMENT:.0f} points apart: "
                 "the machine's noise, or kernel time in the differences)")
    return line
