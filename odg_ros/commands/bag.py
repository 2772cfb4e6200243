"""``odg bag``: write rosbag2 MCAP bags in the nuScenes ROS 2 layout (no ROS install needed).

    odg bag synth --world DIR --out BAG              the synthetic world written by ``odg synth``
    odg bag nuscenes --dataroot DIR --out BAG [--version v1.0-mini] [--scene scene-0061]
    odg bag rig --dataroot DIR --scene S --layout L --out RIG.yaml

One scene gives one bag at BAG. With several scenes selected (several --scene, or none given
and the dataroot has several), each goes to BAG/<scene name>. Topics: see
odg_ros/bags/layout.py. ``rig`` writes the camera rig of a scene's car as a rig file for the
node (rig_file), with the camera names and frames of a bag layout (docs/bags.md).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from .common import UserError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..bags.converters import CONVERTERS

    sub = parser.add_subparsers(dest="source", required=True, metavar="{synth,nuscenes,rig}")
    synth = sub.add_parser("synth", help="bag the synthetic world of `odg synth`")
    synth.add_argument("--world", required=True, type=Path, help="the world folder (a dataroot)")
    nusc = sub.add_parser("nuscenes", help="bag scenes of a nuScenes dataroot")
    nusc.add_argument("--dataroot", required=True, type=Path,
                      help="nuScenes dataroot (holds v1.0-*/, samples/, sweeps/)")
    for p in (synth, nusc):
        p.add_argument("--out", required=True, type=Path, help="bag folder to create")
        p.add_argument("--version", default=None,
                       help="table folder, e.g. v1.0-mini (default: the only one there)")
        p.add_argument("--scene", action="append", default=None,
                       help="scene name; repeat for several (default: all scenes)")
        p.add_argument("--no-lidar", action="store_true", help="leave out /LIDAR_TOP")
        p.add_argument("--force", action="store_true", help="replace existing bags")
    rig = sub.add_parser("rig", help="the camera rig of a scene's car, as a rig file for a "
                                     "bag layout")
    rig.add_argument("--dataroot", required=True, type=Path,
                     help="nuScenes(-format) dataroot (holds v1.0-*/)")
    rig.add_argument("--version", default=None,
                     help="table folder, e.g. v1.0-mini (default: the only one there)")
    rig.add_argument("--scene", required=True, help="scene name, e.g. scene-0061")
    rig.add_argument("--layout", choices=sorted(CONVERTERS), default="odg",
                     help="camera names and frame ids as this converter writes them "
                          "(docs/bags.md)")
    rig.add_argument("--out", required=True, type=Path, help="rig file to write")
    rig.add_argument("--force", action="store_true", help="replace an existing file")


def run(args) -> int:
    from ..bags.nuscenes_source import NuScenesSensorTables
    from ..bags.writer import write_scene_bag

    if args.source == "rig":
        return _write_rig(args)
    dataroot = args.world if args.source == "synth" else args.dataroot
    try:
        tables = NuScenesSensorTables(dataroot, args.version)
        scenes = args.scene or tables.scene_names()
        if not scenes:
            raise ValueError(f"{dataroot}: no scenes")
        outs = ([args.out] if len(scenes) == 1
                else [args.out / scene for scene in scenes])
        for scene, out in zip(scenes, outs):
            records = tables.scene_records(scene, with_lidar=not args.no_lidar)
            summary = write_scene_bag(records, out, force=args.force)
            print(f"{scene} -> {summary}")
    except KeyError as error:      # an unknown scene or table row: a user error here
        raise UserError(error.args[0] if error.args else str(error)) from None
    return 0


def _write_rig(args) -> int:
    from ..bags.converters import CONVERTERS
    from ..bags.nuscenes_source import NuScenesSensorTables
    from ..bags.rig_file import write_rig_file

    try:
        tables = NuScenesSensorTables(args.dataroot, args.version)
        records = tables.scene_records(args.scene, with_lidar=False)
    except KeyError as error:      # an unknown scene: a user error here
        raise UserError(error.args[0] if error.args else str(error)) from None
    source = f"{args.scene} of {args.dataroot / tables.version}"
    out = write_rig_file(records, CONVERTERS[args.layout], source, args.out, force=args.force)
    print(f"{args.scene} ({args.layout} names and frames) -> {out}")
    return 0
