"""``odg prepare``: build the infos index of a nuScenes-format dataroot + Occ3D GT."""
from __future__ import annotations

from .common import UserError, existing_dir


def add_arguments(parser) -> None:
    parser.add_argument("--dataroot", required=True, type=existing_dir,
                        help="nuScenes-format dataroot (tables under <version>/)")
    parser.add_argument("--occ", default=None, type=existing_dir,
                        help="Occ3D gts root (<scene>/<sample>/labels.npz; default "
                             "<dataroot>/gts)")
    parser.add_argument("--out", required=True, help="infos pickle to write")
    parser.add_argument("--version", default="v1.0-trainval",
                        help="table folder: v1.0-trainval, v1.0-mini, ...")
    parser.add_argument("--split", default="train",
                        help="train, val or all (or a nuscenes-devkit split name)")


def run(args) -> int:
    from pathlib import Path

    import numpy as np

    from odg_ros.data.prepare import build_infos, save_infos
    if not (Path(args.dataroot) / args.version).is_dir():
        found = sorted(p.name for p in Path(args.dataroot).glob("v1.0-*"))
        raise UserError(f"{args.dataroot} has no {args.version}/ table folder (found: "
                        f"{', '.join(found) or 'none'}; pick one with --version)")
    infos = build_infos(args.dataroot, args.occ, args.version, args.split)
    items = infos["infos"]
    if not items:
        raise UserError(f"split {args.split!r} of {args.dataroot} has no keyframes; nothing "
                        "written (--split all takes every scene)")
    save_infos(infos, args.out)
    with_occ = sum(bool(i["occ_path"]) for i in items)
    boxes = sum(len(i["gt_labels"]) for i in items)
    sweeps = np.mean([len(i["sweeps"]) for i in items]) if items else 0.0
    print(f"{args.out}: {len(items)} keyframes from {len({i['scene_token'] for i in items})} scenes, "
          f"{with_occ} with Occ3D GT, {boxes} boxes, {sweeps:.1f} earlier camera sets per keyframe")
    if items and with_occ == 0:
        print(f"warning: no labels.npz found under the occ root ({infos['occ_root']})")
    return 0
