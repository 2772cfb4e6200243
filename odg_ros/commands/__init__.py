"""The ``odg`` command (also ``python -m odg_ros.commands``, as torchrun's ``-m`` needs).
Each subcommand lives in ``odg_ros/commands/<name>.py`` with ``add_arguments(parser)`` and
``run(args) -> int``; only the chosen one is imported, so ``odg --help`` stays fast and
ROS-free subcommands never load rclpy.

A user's mistake (a bad option, a missing or foreign file) is one line on stderr,
``odg CMD: error: ...``, and exit code 2; ``--debug`` shows the traceback instead.
"""
from __future__ import annotations

import argparse
import importlib
import sys

SUBCOMMANDS = {
    "info": "model size, Gaussians per layer, FLOPs of a preset",
    "bench": "the node's step per camera set, per stage (and the speed-vs-error sweep)",
    "synth": "generate the synthetic driving world (nuScenes + Occ3D layout)",
    "prepare": "build the infos index from a nuScenes-format dataroot + Occ3D GT",
    "score": "mIoU / RayIoU of saved predictions against the GT",
    "train": "train a preset",
    "profile": "ops and host syncs of a training step, by phase and source line",
    "eval": "run a checkpoint over a split and score it",
    "export": "training checkpoint -> shipped one (compressed, score threshold calibrated)",
    "bag": "write rosbag2 MCAP bags (synth world or nuScenes), or a scene's rig file",
    "replay": "publish rosbag2 bags with rclpy, one after the other",
    "soak": "odg_node fed a loop of scenes for a long while: memory, latency, resets",
    "demo": "the end-to-end demo: world -> bag -> node -> planner stand-in -> scores",
    "ablation": "the ablation table and plot of several odg eval --json results",
}


def build_parser(name: str):
    """The argument parser of ``odg NAME`` (imports only that command's module)."""
    from .common import DefaultsFormatter, Parser
    module = importlib.import_module(f"odg_ros.commands.{name}")
    parser = Parser(prog=f"odg {name}", description=SUBCOMMANDS[name],
                    formatter_class=DefaultsFormatter)
    module.add_arguments(parser)
    for action in parser._actions:          # sub-commands (odg bag synth) format alike
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                sub.formatter_class = DefaultsFormatter
    return module, parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in SUBCOMMANDS:
        width = max(map(len, SUBCOMMANDS))
        lines = [f"  {name:<{width}}  {text}" for name, text in SUBCOMMANDS.items()]
        print("usage: odg [--debug] <command> [options]   (odg <command> --help: its options)"
              "\n\ncommands:\n" + "\n".join(lines))
        if argv and argv[0] not in ("-h", "--help"):
            print(f"odg: error: unknown command {argv[0]!r}", file=sys.stderr)
            return 2
        return 0
    name = argv[0]
    module, parser = build_parser(name)
    try:
        args = parser.parse_args(argv[1:])
    except SystemExit as exit_:             # --help (0) or a bad argument (2), already printed
        return int(exit_.code or 0)
    from .common import USER_ERRORS
    try:
        return int(module.run(args) or 0)
    except KeyboardInterrupt:
        print(f"odg {name}: interrupted", file=sys.stderr)
        return 130
    except USER_ERRORS as error:
        if debug:
            raise
        print(f"odg {name}: error: {one_line(error)}", file=sys.stderr)
        return 2


def one_line(error: BaseException) -> str:
    text = " ".join(str(error).split())
    if isinstance(error, OSError) and error.filename and str(error.filename) not in text:
        text = f"{text}: {error.filename}"
    return text or type(error).__name__
