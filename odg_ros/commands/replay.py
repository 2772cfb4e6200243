"""``odg replay BAG [BAG ...]``: publish rosbag2 bags with rclpy (for machines without rosbag2).

    odg replay BAG [BAG ...] [--rate R] [--clock] [--loop] [--topics T [T ...]]
               [--remap OLD:=NEW [OLD:=NEW ...]] [--wait-for-subscribers S] [--network]

Each BAG is a bag folder, an .mcap file or a folder of bags; they play back to back. DDS
stays on this machine (odg_ros.ros.dds) unless --network is given.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .common import nonnegative_float, positive_float


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bags", type=Path, nargs="+", metavar="BAG",
                        help="rosbag2 folder (MCAP or SQLite 3), .mcap file, or a folder of "
                             "bags; several play back to back, in the order given (a folder's "
                             "bags in name order)")
    parser.add_argument("--rate", type=positive_float, default=1.0,
                        help="playback speed factor (default 1.0 = real time)")
    parser.add_argument("--clock", action="store_true",
                        help="also publish the bag time on /clock (for use_sim_time nodes)")
    parser.add_argument("--loop", action="store_true",
                        help="start over at the end of the last bag, until Ctrl-C")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", default=None,
                        help="publish only these topics, as the bags name them (default: all)")
    parser.add_argument("--remap", "-m", nargs="+", metavar="OLD:=NEW", default=[],
                        action="extend",
                        help="rename topics as they are published, ROS remapping rules "
                             "(e.g. /diagnostics:=/can/diagnostics; default: none)")
    parser.add_argument("--wait-for-subscribers", type=nonnegative_float, default=0.0,
                        metavar="S",
                        help="before publishing, wait up to S seconds until every topic has a "
                             "subscriber (default 0: start at once)")
    parser.add_argument("--network", action="store_true",
                        help="use the RMW's default discovery (other machines can receive) "
                             "instead of this machine only")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    if not args.network:
        from ..ros.dds import use_localhost_dds
        use_localhost_dds()  # before rclpy is initialised
    from ..ros.replay import replay

    def say(line: str) -> None:
        print(f"odg replay: {line}", file=sys.stderr, flush=True)

    stats = replay(args.bags, rate=args.rate, clock=args.clock, loop=args.loop,
                   topics=args.topics, remap=args.remap,
                   wait_for_subscribers_s=args.wait_for_subscribers, progress=not args.quiet,
                   say=say)
    print(stats)
    return 130 if stats.interrupted else 0
