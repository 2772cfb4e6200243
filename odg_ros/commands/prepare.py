"""``odg prepare``: build the infos index of a nuScenes-format dataroot + Occ3D-nuScenes GT,
or (``--layout waymo``) of Occ3D-Waymo (odg_ros/data/prepare_waymo.py)."""
from __future__ import annotations

from .common import UserError, existing_dir, positive_float, positive_int


def add_arguments(parser) -> None:
    parser.add_argument("--dataroot", required=True, type=existing_dir,
                        help="nuScenes-format dataroot (tables under <version>/); waymo: the "
                             "folder holding training/image_0..4/ (mmdetection3d's kitti_format)")
    parser.add_argument("--occ", default=None, type=existing_dir,
                        help="Occ3D GT root (nuscenes: <scene>/<sample>/labels.npz, default "
                             "<dataroot>/gts; waymo: the Occ3D-Waymo folder with cam_infos*.pkl "
                             "and training/, validation/, default <dataroot>)")
    parser.add_argument("--out", required=True, help="infos pickle to write")
    parser.add_argument("--layout", choices=("nuscenes", "waymo"), default="nuscenes",
                        help="dataset layout (default nuscenes)")
    parser.add_argument("--version", default="v1.0-trainval",
                        help="nuscenes: table folder: v1.0-trainval, v1.0-mini, ...")
    parser.add_argument("--split", default="train",
                        help="train, val or all (or a nuscenes-devkit split name); waymo: "
                             "train or val")
    parser.add_argument("--keyframe-interval", type=positive_int, default=1,
                        help="waymo: every Nth frame is a keyframe, the frames between are its "
                             "history (default 1: every frame)")
    parser.add_argument("--frame-hz", type=positive_float, default=10.0,
                        help="waymo: frames per second (the pose files hold no stamps; "
                             "default 10, Waymo's rate)")


def run(args) -> int:
    from pathlib import Path

    import numpy as np

    from ..data.prepare import build_infos, save_infos
    if args.layout == "waymo":
        from ..data.prepare_waymo import build_waymo_infos
        try:
            infos, notes = build_waymo_infos(args.dataroot, args.occ, args.split,
                                             args.keyframe_interval, args.frame_hz)
        except (FileNotFoundError, ValueError) as error:
            raise UserError(str(error)) from None
        for note in notes:
            print(f"note: {note}")
    else:
        if not (Path(args.dataroot) / args.version).is_dir():
            found = sorted(p.name for p in Path(args.dataroot).glob("v1.0-*"))
            raise UserError(f"{args.dataroot} has no {args.version}/ table folder (found: "
                            f"{', '.join(found) or 'none'}; pick one with --version, or "
                            f"--layout waymo for Occ3D-Waymo)")
        infos = build_infos(args.dataroot, args.occ, args.version, args.split)
    items = infos["infos"]
    if not items:
        raise UserError(f"split {args.split!r} of {args.dataroot} has no keyframes; nothing "
                        "written" + (" (--split all takes every scene)"
                                     if args.layout == "nuscenes" else ""))
    save_infos(infos, args.out)
    with_occ = sum(bool(i["occ_path"]) for i in items)
    boxes = sum(len(i["gt_labels"]) for i in items)
    sweeps = np.mean([len(i["sweeps"]) for i in items]) if items else 0.0
    print(f"{args.out}: {len(items)} keyframes from {len({i['scene_token'] for i in items})} scenes, "
          f"{with_occ} with Occ3D GT, {boxes} boxes, {sweeps:.1f} earlier camera sets per keyframe")
    if items and with_occ == 0:
        print(f"warning: no Occ3D GT file found under the occ root ({infos['occ_root']})")
    return 0
