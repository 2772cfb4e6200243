"""``odg synth``: generate the synthetic driving world (docs/SYNTH.md)."""
from __future__ import annotations

import os

# The generator is single-threaded NumPy; keep BLAS from spreading small matmuls over cores.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


def add_arguments(parser) -> None:
    from ..data.synth.generate import DEFAULT_IMAGE_HW

    from .common import positive_float, positive_int
    parser.add_argument("--out", required=True,
                        help="output dataroot (must not hold this version yet)")
    parser.add_argument("--scenes", type=positive_int, default=8,
                        help="number of scenes (every 4th goes to val: 4 or more gives a val "
                             "split; the default takes about 5 minutes on one core)")
    parser.add_argument("--seconds", type=positive_float, default=6.0,
                        help="length of each scene (2 keyframes/s)")
    parser.add_argument("--seed", type=int, default=0, help="same seed, same bytes")
    parser.add_argument("--image-size", type=positive_int, nargs=2, default=list(DEFAULT_IMAGE_HW), metavar=("H", "W"),
                        help="camera image size (intrinsics are the nuScenes ones scaled from 900 x 1600)")
    parser.add_argument("--version", default="v1.0-trainval", help="name of the table folder")
    parser.add_argument("--traffic", choices=("quiet", "normal", "dense"), default="normal",
                        help="how many vehicles, cyclists and pedestrians: quiet (about a third "
                             "of normal), normal, dense (default: normal)")
    parser.add_argument("--roads", choices=("city", "open-road"), default="city",
                        help="city: a grid of roads between blocks of buildings, parks and "
                             "parking lots; open-road: one road through countryside, no "
                             "crossings (default: city)")
    parser.add_argument("--layout", choices=("nuscenes", "waymo"), default="nuscenes",
                        help="nuscenes (tables, six cameras, Occ3D-nuScenes GT) or waymo (the "
                             "Occ3D-Waymo layout: five cameras, Waymo labels, one frame per "
                             "keyframe) (default: nuscenes)")


def run(args) -> int:
    from ..data.synth.city import SceneKind
    from ..data.synth.generate import generate
    options = dict(scenes=args.scenes, seconds=args.seconds, seed=args.seed,
                   image_hw=tuple(args.image_size), version=args.version,
                   kind=SceneKind(args.traffic, args.roads))
    if args.layout == "waymo":
        from ..data.synth.waymo_layout import generate_waymo
        summary = generate_waymo(args.out, **options)
        print(f"wrote {summary['split']['train']} training and {summary['split']['val']} "
              f"validation scenes in the Occ3D-Waymo layout to {args.out} in "
              f"{summary['seconds']:.0f} s; next: odg prepare --layout waymo --frame-hz 2 "
              f"--dataroot {args.out} --split train --out {args.out}/infos_train.pkl")
        return 0
    summary = generate(args.out, **options)
    print(f"wrote {summary['scenes']} scenes, {summary['keyframes']} keyframes, {summary['images']} images, "
          f"{summary['lidar_sweeps']} LiDAR sweeps to {args.out} in {summary['seconds']:.0f} s "
          f"({summary['bytes'] / 2 ** 20:.0f} MiB)")
    print(f"train: {len(summary['split']['train'])} scenes, val: {len(summary['split']['val'])} scenes "
          f"(splits.json); next: odg prepare --dataroot {args.out} --out {args.out}/infos_train.pkl")
    return 0
