"""The node's step with this code's padding and visibility against the step with those of a
git revision, side by side in one run: each stage's CPU time, the step's, and their shares.

    python -m tools.stage_times_against --data data/held_out/city-normal/infos_all.pkl \
        [--checkpoint model/odg_cpu.pt] [--against main] [--sets 12] [--warmup 2]

Two predictors at the node's settings (``node_settings``: shipped precision, padding,
calibration, visibility) step over the first --sets keyframes of the first scene of --data,
taking turns set by set (the order alternating), one torch thread, each step's marks
recorded in the CPU time of the thread that runs it (as ``odg bench --shares``). The
"before" predictor is this code with its ``padding`` and ``visibility`` modules replaced by
those of --against (``network/padding.py``, ``network/visibility.py`` there). Before the
timing both grids and observed masks are compared: they must be the same bit for bit (exit
1 otherwise). Prints JSON: per side the median step and stage times (ms), the shares by the
marks, and the median per-set ratios after / before.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch
from tqdm import tqdm

from tools.revision import module_at, report


def before_modules(step, cfg, against: str) -> None:
    """Replace ``step``'s padding and visibility (an OnlineStep) by those at ``against``."""
    padding = module_at(against, "odg_ros/network/padding.py")
    visibility = module_at(against, "odg_ros/network/visibility.py")
    new = step.visibility
    step.padding = padding.OccupancyPadding(cfg.grid_shape, step.free_label,
                                            cfg.score_threshold, "cpu")
    step.visibility = visibility.Visibility(cfg.grid_shape, cfg.pc_range, cfg.voxel_size,
                                            step.free_label, new.min_clear, device="cpu")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="infos .pkl (its first scene)")
    parser.add_argument("--checkpoint", default="model/odg_cpu.pt")
    parser.add_argument("--against", default="main", help="git revision (default main)")
    parser.add_argument("--sets", type=int, default=12, help="timed camera sets")
    parser.add_argument("--warmup", type=int, default=2, help="untimed sets first")
    args = parser.parse_args(argv)
    from odg_ros.bench.step_timing import data_camera_sets, node_predictor, node_settings
    from odg_ros.network.checkpoint import load_model
    from odg_ros.online.marks import MarkRecorder
    torch.set_num_threads(1)
    model, cfg = load_model(args.checkpoint, device="cpu")
    count = args.warmup + args.sets
    sets = data_camera_sets(args.data, cfg, count)
    sets = [sets[i % len(sets)] for i in range(count)]
    settings = node_settings()
    predictors = {"after": node_predictor(model, cfg, "cpu", settings),
                  "before": node_predictor(model, cfg, "cpu", settings)}
    if any(p.mode != "eager" for p in predictors.values()):
        raise SystemExit("stage_times_against: the node's step is not eager here (no marks)")
    before_modules(predictors["before"].online_step, cfg, args.against)
    recorders = {name: MarkRecorder("cpu", clock=time.thread_time) for name in predictors}
    steps = {name: [] for name in predictors}
    differ = 0
    with torch.inference_mode():
        for i in tqdm(range(count), desc="steps"):
            order = list(predictors) if i % 2 == 0 else list(predictors)[::-1]
            outputs = {}
            for name in order:
                start = time.thread_time()
                with recorders[name]:
                    outputs[name] = predictors[name].step(*sets[i])
                if i >= args.warmup:
                    steps[name].append(1e3 * (time.thread_time() - start))
            if i < args.warmup:
                for recorder in recorders.values():
                    recorder.times.clear()
            a, b = outputs["after"], outputs["before"]
            fields = ("grid", "confidence", "observed")
            differ += sum(not torch.equal(torch.as_tensor(getattr(a, f)),
                                          torch.as_tensor(getattr(b, f))) for f in fields)
    stages = ("padding", "visibility")
    result = {"against": args.against, "data": args.data, "sets": args.sets, "threads": 1,
              "outputs_differ": differ}
    for name in predictors:
        marks = recorders[name].times
        result[name] = {
            "step_ms": round(statistics.median(steps[name]), 1),
            **{f"{s}_ms": round(statistics.median(marks[s]), 2) for s in stages},
            "shares_by_marks": {s: round(statistics.median(
                m / t for m, t in zip(marks[s], steps[name])), 4) for s in stages},
        }
        result[name]["together_by_marks"] = round(sum(result[name]["shares_by_marks"].values()), 4)
    result["after_over_before"] = {
        s: round(statistics.median(a / b for a, b in zip(recorders["after"].times[s],
                                                         recorders["before"].times[s])), 3)
        for s in stages}
    result["after_over_before"]["step"] = round(statistics.median(
        a / b for a, b in zip(steps["after"], steps["before"])), 3)
    return report(result, differ and f"stage_times_against: {differ} outputs differ")


if __name__ == "__main__":
    sys.exit(main())
