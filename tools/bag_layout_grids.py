"""The same grid whatever the converter, with a real model: one synthetic world (keyframe gaps
0.55 and 0.75 s) as a bag of `odg bag` and of each public converter's layout
(testing/bag_layouts.py), each run deterministically through the node's pipeline with the
layout's documented params file (testing/bag_pipeline.py), grids compared set by set with
those of the `odg bag` bag that carries the same information: the world's, or for
`foxglove tf` (ego poses only at keyframes) the world with its keyframe poses interpolated;
`foxglove tf` is also compared with the world's true poses (the interpolation error).

    python -m tools.bag_layout_grids                          # shipped model, a new world
    python -m tools.bag_layout_grids --world /tmp/layouts     # keep / reuse the world there
    python -m tools.bag_layout_grids --checkpoint runs/odg_t.pt --image-size 198 352

Prints per layout the sets run, the inputs refused, and the agreement with `odg bag` over
all voxels and over the voxels occupied in either grid (min and median over the sets), then
the same as JSON.
"""
from __future__ import annotations

import argparse
import json
import pickle
from pathlib import Path

import numpy as np
import torch

from odg_ros.classes import FREE_LABEL
from odg_ros.network.checkpoint import load_model
from odg_ros.online.predictor import OnlinePredictor
from odg_ros.resources import shipped_checkpoint
from testing.bag_layouts import build_layout_world, keyframe_gaps
from testing.bag_pipeline import VARIANTS, layout_parameters, run_bag, variant_bag


def agreement(grids: dict, reference: dict) -> dict:
    all_voxels, occupied = [], []
    for stamp, grid in grids.items():
        if stamp not in reference:
            continue
        ref = reference[stamp]
        either = (grid != FREE_LABEL) | (ref != FREE_LABEL)
        all_voxels.append(float(np.mean(grid == ref)))
        occupied.append(float(np.mean(grid[either] == ref[either])))

    def summary(values):
        return {"min": min(values), "median": float(np.median(values))} if values else None
    return {"sets_compared": len(all_voxels), "all_voxels": summary(all_voxels),
            "occupied_voxels": summary(occupied)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", type=Path, default=None,
                        help="folder for the world and its bags (built once, then reused)")
    parser.add_argument("--checkpoint", default=None, help="default: the shipped model")
    parser.add_argument("--image-size", type=int, nargs=2, default=(45, 80),
                        metavar=("H", "W"), help="camera image size of a new world")
    parser.add_argument("--every", type=int, default=3, help="run every n-th camera set")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)

    if args.world is None:
        import tempfile
        args.world = Path(tempfile.mkdtemp(prefix="bag_layouts_"))
    cached = args.world / "world.pkl"
    if cached.is_file():
        world = pickle.loads(cached.read_bytes())
    else:
        world = build_layout_world(args.world, image_hw=tuple(args.image_size))
        cached.write_bytes(pickle.dumps(world))
    model, cfg = load_model(args.checkpoint or shipped_checkpoint(), device="cpu")
    only = set(world.camera_sets_us(every=args.every))
    runs = {}
    for variant in VARIANTS:
        predictor = OnlinePredictor(model, cfg, "cpu", min_interval=0.45, visibility=False)
        runs[variant] = run_bag(variant_bag(world, variant), predictor,
                                layout_parameters(world, variant), only_us=only)
    report = {"world": str(args.world), "keyframe_gaps_s": keyframe_gaps(world.records),
              "model": cfg.name, "sets": len(only), "layouts": {}}
    compared = [(v, "odg keyframe poses" if v == "foxglove tf" else "odg") for v in VARIANTS
                if v != "odg"] + [("foxglove tf", "odg")]
    for variant, reference in compared:
        run = runs[variant]
        entry = {"against": reference, "sets_run": len(run.grids),
                 "refused": dict(run.skipped),
                 "stale_sets_dropped": run.counters["stale_sets_dropped"]}
        entry.update(agreement(run.grids, runs[reference].grids))
        report["layouts"][f"{variant} against {reference}"] = entry
        a, o = entry["all_voxels"], entry["occupied_voxels"]
        print(f"{variant:12s} against {reference:18s} sets {len(run.grids):3d}  refused "
              f"{dict(run.skipped) or '-'}  "
              + (f"all voxels min {100 * a['min']:.3f} % median {100 * a['median']:.3f} %  "
                 f"occupied min {100 * o['min']:.2f} % median {100 * o['median']:.2f} %"
                 if a else "nothing to compare"))
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
