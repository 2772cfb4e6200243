"""The node's rate next to its step's, in one run: the step alone, then the node replaying.

1. The demo world (``odg demo``'s scene, built or reused under --out) and its bag.
2. The step alone: ``OnlinePredictor.step`` at the node's settings (shipped checkpoint,
   --precision, padding and visibility on, full query budget, torch's default threads),
   over the scene's keyframes in order (history as in the node), --steps of them after two
   warm-up steps: wall and CPU time per step (medians). Then the padding's and the
   visibility's shares of the step's CPU time, on one thread (what other processes on the
   machine inflate least) and on the step's own threads, two ways side by side
   (``odg_ros/bench/stage_shares.py``, as ``odg bench --shares``): from the step's own
   marks, and from the step without each, set by set interleaved with the full one;
   medians of the per-set ratios.
3. The node: ``odg_node`` in its own process, the bag replayed into it by ``odg replay
   --clock --rate R`` over loopback DDS (what ``odg demo`` runs); R high enough that sets
   come faster than the node takes them, so it runs back to back. Its grids per second as
   a planner receives them, and its own ``/diagnostics`` stage times.

    python -m tools.node_rate [--out out/demo] [--rate 0.5] [--precision auto] [--step-only]
        [--threads N] [--no-shares] [--json]

Prints both with their ratios (node ``stage_model_ms`` / step wall time; node grids per
second / step rate), the load average before and after (the machine may be shared), how
much faster a matrix product ran on all cores than on one just before and after
(``odg_ros/bench/core_scaling.py``: on a shared machine the other cores come and go) and
the CPU. The node part needs the ROS 2 Python packages (``make setup``), as ``odg demo``
does; --step-only leaves it out.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def keyframe_inputs(infos: Path, cfg) -> list:
    """(images, ego2img, pose, stamp, bounds) of the world's keyframes, in order (the node
    decodes the same images from the bag)."""
    from odg_ros.data.dataset import OccDataset
    from odg_ros.preprocess import image_bounds

    dataset = OccDataset(str(infos), cfg)
    names = dataset.camera_names
    inputs = []
    for info in dataset.infos:
        ego2img, _, _ = dataset.frame_geometry(info["cams"], np.asarray(info["ego_pose"]))
        inputs.append((np.stack([dataset.load_image(info["cams"][c]) for c in names]),
                       ego2img, np.asarray(info["ego_pose"]), info["timestamp"] * 1e-6,
                       image_bounds([info["cams"][c]["image_hw"] for c in names],
                                    dataset.image_size)))
    return inputs


def step_inputs(inputs: list, i: int):
    """Set i of an endless drive over the keyframes (past the end the stamps go on)."""
    images, ego2img, pose, stamp, bounds = inputs[i % len(inputs)]
    return images, ego2img, pose, stamp + (i // len(inputs)) * (len(inputs) + 1) * 0.5, bounds


def time_step(checkpoint: Path, infos: Path, precision: str, steps: int, log,
              shares: bool = True) -> dict:
    """The node's step alone: wall and CPU time per step at the node's settings; then the
    padding's and the visibility's shares of its CPU time (bench/stage_shares.py: by the
    step's marks and by the step without each, set by set interleaved), on one thread and
    on the step's own threads."""
    import torch

    from odg_ros.bench.stage_shares import stage_shares
    from odg_ros.bench.step_timing import node_predictor, node_settings
    from odg_ros.network.checkpoint import load_model

    if os.environ.get("OMP_NUM_THREADS"):
        torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    model, cfg = load_model(checkpoint, device="cpu")
    inputs = keyframe_inputs(infos, cfg)

    settings = node_settings(precision=precision)
    threads = torch.get_num_threads()
    sets = [step_inputs(inputs, i) for i in range(steps + 2)]

    def stage_shares_at(n):
        return stage_shares(model, cfg, sets, settings, threads=n, progress=False)
    # one thread first: once torch has run on more, an OpenMP worker left spinning after
    # a parallel region can add its kernel time to a one-thread step (and it did, to the
    # step with the visibility more than to the one without)
    one_thread = [stage_shares_at(1)] if shares and threads > 1 else []
    node = node_predictor(model, cfg, "cpu", settings)
    wall, cpu = [], []
    for i in range(steps + 2):
        images, ego2img, pose, stamp, bounds = step_inputs(inputs, i)
        start, start_cpu = time.perf_counter(), time.process_time()
        node.step(images, ego2img, pose, stamp, bounds=bounds)
        if i >= 2:                                                    # two warm-up steps
            wall.append(time.perf_counter() - start)
            cpu.append(time.process_time() - start_cpu)
        log(f"step {i + 1}/{steps + 2}: {1e3 * (time.perf_counter() - start):.0f} ms")
    shares = one_thread + [stage_shares_at(threads)] if shares else []
    step_ms = 1e3 * statistics.median(wall)
    return {"precision": node.precision, "mode": node.mode,
            "threads": threads, "steps": len(wall),
            "step_ms_median": round(step_ms, 1),
            "cpu_ms_median": round(1e3 * statistics.median(cpu), 1),
            "steps_per_s": round(1e3 / step_ms, 2), "shares": shares}


def run_node(world, checkpoint: Path, out: Path, rate: float, precision: str, log) -> dict:
    from odg_ros.demo.records import bag_camera_sets
    from odg_ros.demo.report import node_numbers, output_and_input_fps
    from odg_ros.ros.demo_session import run_session

    sets = bag_camera_sets(world.bag)
    record = run_session(world.bag, checkpoint, sets, out, rate, log=log, precision=precision)
    fps, input_fps = output_and_input_fps(record, sets)
    node = node_numbers(record)
    return {"grids_per_s": None if fps is None else round(fps, 2),
            "input_sets_per_s": None if input_fps is None else round(input_fps, 2),
            "grids_out": len(record.grids), "sets_in": int(sets.num_complete),
            "stage_ms": node["stage_ms"], "fps_topic_median": node["fps_topic_median"]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/demo"),
                        help="the demo world's folder (built there if missing; default "
                             "out/demo, odg demo's)")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="default: the shipped model/odg_cpu.pt")
    parser.add_argument("--rate", type=float, default=0.5,
                        help="replay speed, x real time (default 0.5: 6 camera sets per "
                             "second, more than the CPU node takes)")
    parser.add_argument("--precision", default="auto",
                        help="the node's precision parameter (default auto, the node's)")
    parser.add_argument("--steps", type=int, default=16,
                        help="steps timed alone, after two warm-up steps (default 16)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads of the step and the node (OMP_NUM_THREADS; "
                             "default: torch's, one per core)")
    parser.add_argument("--step-only", action="store_true",
                        help="time the step alone, no node (no ROS 2 needed)")
    parser.add_argument("--no-shares", action="store_true",
                        help="leave out the padding's and the visibility's shares")
    parser.add_argument("--json", action="store_true", help="print JSON only")
    args = parser.parse_args(argv)

    def log(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    if args.threads:      # before torch loads, here and in the node's process
        os.environ["OMP_NUM_THREADS"] = str(args.threads)

    from odg_ros.bench.core_scaling import core_scaling, format_scaling
    from odg_ros.bench.stage_shares import format_shares
    from odg_ros.data.synth.generate import DEFAULT_IMAGE_HW
    from odg_ros.demo.demo_world import WorldSpec, build_demo_world, resolve_checkpoint

    checkpoint = resolve_checkpoint(args.checkpoint)
    world = build_demo_world(args.out, WorldSpec(image_hw=tuple(DEFAULT_IMAGE_HW)), log=log)
    load_before = os.getloadavg()
    scaling_before = core_scaling()
    step = time_step(checkpoint, world.infos, args.precision, args.steps, log,
                     not args.no_shares)
    node = {"grids_per_s": None, "stage_ms": {}} if args.step_only else \
        run_node(world, checkpoint, args.out, args.rate, args.precision, log)
    scaling_after = core_scaling()
    model_ms = node["stage_ms"].get("model")
    result = {
        "date": date.today().isoformat(), "cpu": cpu_name(), "cores": os.cpu_count(),
        "load_average_before": [round(v, 2) for v in load_before],
        "load_average_after": [round(v, 2) for v in os.getloadavg()],
        "core_scaling": {"before": scaling_before, "after": scaling_after},
        "checkpoint": str(checkpoint), "rate": args.rate, "step": step, "node": node,
        # the node's model stage against the step alone: 1.0 when nothing else slows it
        "node_model_ms_over_step_ms": (round(model_ms / step["step_ms_median"], 3)
                                       if model_ms else None),
        "node_grids_per_s_over_step_rate": (
            round(node["grids_per_s"] / step["steps_per_s"], 3)
            if node["grids_per_s"] else None),
    }
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"{result['date']}, {result['cpu']} ({result['cores']} cores), load average "
          f"{load_before[0]:.1f} before, {result['load_average_after'][0]:.1f} after")
    print(format_scaling(scaling_before, scaling_after))
    print(f"step alone ({step['precision']}, {step['mode']}, {step['threads']} threads): "
          f"{step['step_ms_median']:.0f} ms wall ({step['steps_per_s']:.2f} steps/s), "
          f"{step['cpu_ms_median']:.0f} ms CPU, median of {step['steps']}")
    for shares in step["shares"]:
        print(format_shares(shares))
    if args.step_only:
        return 0
    stages = ", ".join(f"{k} {v:.0f}" for k, v in node["stage_ms"].items() if v is not None)
    print(f"node replaying at {args.rate:g}x ({node['input_sets_per_s']} sets/s in): "
          f"{node['grids_per_s']} grids/s out ({node['grids_out']} of {node['sets_in']}); "
          f"stage ms: {stages}")
    print(f"node model stage / step alone: {result['node_model_ms_over_step_ms']}; node "
          f"grids/s / step rate: {result['node_grids_per_s_over_step_rate']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
