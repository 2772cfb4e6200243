"""The ``odg`` command. Each subcommand lives in ``odg_ros/commands/<name>.py`` with
``add_arguments(parser)`` and ``run(args) -> int``; only the chosen one is imported, so
``odg --help`` stays fast and ROS-free subcommands never load rclpy."""
from __future__ import annotations

import argparse
import importlib
import sys

SUBCOMMANDS = {
    "info": "model size, Gaussians per layer, FLOPs of a preset",
    "bench": "latency of one online step per stage (and the speed-vs-error sweep)",
    "synth": "generate the synthetic driving world (nuScenes + Occ3D layout)",
    "prepare": "build the infos index from a nuScenes-format dataroot + Occ3D GT",
    "score": "mIoU / RayIoU of saved predictions against the GT",
    "train": "train a preset",
    "eval": "run a checkpoint over a split and score it",
    "export": "training checkpoint -> shipped one (compressed, score threshold calibrated)",
    "bag": "write rosbag2 MCAP bags (synth world or nuScenes)",
    "replay": "publish a rosbag2 bag with rclpy",
    "demo": "the end-to-end demo: world -> bag -> node -> planner stand-in -> scores",
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in SUBCOMMANDS:
        width = max(map(len, SUBCOMMANDS))
        lines = [f"  {name:<{width}}  {text}" for name, text in SUBCOMMANDS.items()]
        print("usage: odg <command> [options]\n\ncommands:\n" + "\n".join(lines))
        if argv and argv[0] not in ("-h", "--help"):
            print(f"\nodg: unknown command {argv[0]!r}", file=sys.stderr)
            return 2
        return 0
    name = argv[0]
    module = importlib.import_module(f"odg_ros.commands.{name}")
    parser = argparse.ArgumentParser(prog=f"odg {name}", description=SUBCOMMANDS[name])
    module.add_arguments(parser)
    args = parser.parse_args(argv[1:])
    return int(module.run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
