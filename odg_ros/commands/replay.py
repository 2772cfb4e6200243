"""``odg replay BAG``: publish a rosbag2 bag with rclpy (for machines without rosbag2).

    odg replay BAG [--rate R] [--clock] [--loop] [--wait-for-subscribers S] [--network]

DDS stays on this machine (odg_ros.ros.dds) unless --network is given.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from .common import UserError, nonnegative_float, positive_float


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="rosbag2 folder (MCAP or SQLite 3)")
    parser.add_argument("--rate", type=positive_float, default=1.0,
                        help="playback speed factor (default 1.0 = real time)")
    parser.add_argument("--clock", action="store_true",
                        help="also publish the bag time on /clock (for use_sim_time nodes)")
    parser.add_argument("--loop", action="store_true", help="start over at the end, until Ctrl-C")
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
        from odg_ros.ros.dds import use_localhost_dds
        use_localhost_dds()  # before rclpy is initialised
    from odg_ros.ros.replay import replay

    if not (args.bag / "metadata.yaml").is_file():
        raise UserError(f"{args.bag} is not a rosbag2 folder (no metadata.yaml)")
    stats = replay(args.bag, rate=args.rate, clock=args.clock, loop=args.loop,
                   wait_for_subscribers_s=args.wait_for_subscribers, progress=not args.quiet)
    print(stats)
    return 130 if stats.interrupted else 0
