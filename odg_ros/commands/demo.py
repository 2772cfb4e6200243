"""``odg demo``: the main job, end to end on this machine (no GPU, no ROS install).

    odg demo [--out out/demo] [--checkpoint CKPT] [--seed 1000] [--seconds 8] [--rate 0.25]
             [--image-size H W] [--device D] [--json]

1. a synthetic world of one scene (``odg synth``, a seed the training world does not use),
   its infos (``odg prepare --split all``) and a rosbag2 bag of it (``odg bag synth``);
   reused on the next run when the settings are the same;
2. ``odg_node`` in its own process with the shipped checkpoint and simulated time, the bag
   replayed by ``odg replay --clock`` in another, over real DDS on loopback;
3. a planner stand-in (this process) receives every output; the keyframe grids are scored
   against the GT (mIoU, RayIoU);
4. a table (``--json``: the numbers as JSON only), and always ``demo.json`` + ``demo.png``
   (cameras + BEV prediction vs GT) in the output folder. What each number means:
   odg_ros/demo/__init__.py.
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..demo.demo_world import DEFAULT_OUT, DEFAULT_RATE, DEFAULT_SECONDS, DEFAULT_SEED

    from .common import add_device_option, add_json_option, existing_file, positive_float, \
        positive_int

    parser.add_argument("--out", type=Path, default=DEFAULT_OUT,
                        help=f"folder of the world, bag, logs, demo.json and demo.png "
                             f"(default {DEFAULT_OUT}); a world built there before with the "
                             "same settings is reused")
    parser.add_argument("--checkpoint", type=existing_file, default=None,
                        help="model checkpoint (default: the shipped model/odg_cpu.pt)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED,
                        help=f"seed of the synthetic scene (default {DEFAULT_SEED}; the "
                             "seeds the shipped model trained on are in model/odg_cpu.md)")
    parser.add_argument("--seconds", type=positive_float, default=DEFAULT_SECONDS,
                        help=f"length of the scene (default {DEFAULT_SECONDS:g}; 2 keyframes/s)")
    parser.add_argument("--image-size", type=positive_int, nargs=2, default=None, metavar=("H", "W"),
                        help="camera image size of the scene (default: odg synth's)")
    parser.add_argument("--rate", type=positive_float, default=DEFAULT_RATE,
                        help=f"replay speed, x real time (default {DEFAULT_RATE:g}: 12 Hz "
                             "camera sets every 333 ms, about what the CPU model keeps up with)")
    # network/precision.PRECISIONS, not imported here: `odg demo --help` stays torch-free
    parser.add_argument("--precision",
                        choices=("auto", "fp32", "bf16-encoder", "int8-encoder", "bf16", "fp16"),
                        default="auto",
                        help="the node's precision parameter (default auto, the node's: "
                             "bf16-encoder on a CPU with AVX512-BF16/AMX, else fp32)")
    add_device_option(parser, help="the node's device: auto (cuda when available), cpu, cuda "
                                   "or cuda:N")
    add_json_option(parser, help="print the numbers as JSON only (progress still goes to stderr)")


def run(args) -> int:
    def log(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    # SIGTERM (a CI timeout, kill) ends the demo like Ctrl-C: its children are stopped.
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        return _run(args, log)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _run(args, log) -> int:
    from ..data.synth.generate import DEFAULT_IMAGE_HW
    from ..demo import REFERENCE_CAMERA, DemoError
    from ..demo.picture import draw_demo_png, pick_keyframe
    from ..demo.records import bag_camera_sets
    from ..demo.report import format_summary, score_keyframes, summarize_session, write_json
    from ..demo.demo_world import WorldSpec, build_demo_world, resolve_checkpoint

    started = time.monotonic()
    out = args.out
    timings = {}
    try:
        checkpoint = resolve_checkpoint(args.checkpoint)
        spec = WorldSpec(seed=args.seed, seconds=args.seconds,
                              image_hw=tuple(args.image_size or DEFAULT_IMAGE_HW))
        world = build_demo_world(out, spec, log=log)
        timings["world" + (" (reused)" if world.reused else "")] = world.seconds
        sets = bag_camera_sets(world.bag)

        try:                                                # rclpy from here on
            from ..ros.demo_session import run_session
            import odg_ros_msgs.msg  # noqa: F401
            import rclpy  # noqa: F401
        except ImportError as error:
            raise DemoError(f"the ROS 2 Python packages are not importable ({error}); "
                                 "run `make setup`") from None
        record = run_session(world.bag, checkpoint, sets, out, args.rate, log=log,
                             precision=args.precision, device=args.device)
        timings["node start"] = record.timings["node_start"]
        timings["replay"] = record.timings["replay"]
        timings["drain"] = record.timings["drain"]

        if not record.grids:
            raise DemoError(f"the node published no occupancy grid (see {out}/node.log); "
                                 f"its last diagnostics: {record.diagnostics_message!r}")
        start = time.monotonic()
        from ..metrics.score import load_scoring_infos
        meta = load_scoring_infos(world.infos)
        grids = {g.stamp_ns: g.labels for g in record.grids}
        score, scored, per_keyframe = score_keyframes(meta, grids)
        timings["scoring"] = time.monotonic() - start

        report = summarize_session(record, sets, meta, score, scored, args.rate)
        report["checkpoint"] = str(checkpoint)
        report["precision"] = args.precision
        report["device"] = args.device
        report["world"] = spec.as_dict()
        report["out"] = str(out)
        if scored:
            start = time.monotonic()
            index = pick_keyframe(scored, meta["infos"])
            stamp = int(meta["infos"][index]["cams"][REFERENCE_CAMERA]["timestamp"]) * 1000
            observed = {g.stamp_ns: g.observed for g in record.grids}
            draw_demo_png(out / "demo.png", meta, index, grids[stamp], report,
                          per_keyframe[index], observed[stamp])
            timings["picture"] = time.monotonic() - start
        else:
            report["warnings"].append("no keyframe grid arrived: nothing scored, no demo.png")
        timings["total"] = time.monotonic() - started
        report["timings_s"] = {k: round(v, 1) for k, v in timings.items()}
        write_json(report, out / "demo.json")
    except DemoError as error:
        log(f"odg demo: {error}")
        return 1
    except KeyboardInterrupt:
        log("odg demo: interrupted")
        return 130

    if args.json:
        import json
        print(json.dumps(report, indent=2, allow_nan=False))
    else:
        if score is not None:
            from ..metrics.score import format_table
            print(format_table(score) + "\n")
        print(format_summary(report))
        files = [out / "demo.json"] + ([out / "demo.png"] if scored else []) + [out / "node.log"]
        print("files: " + ", ".join(str(f) for f in files))
    return 0
