"""The visibility of this code against the one at a git revision, on the node's own grids:
the same observed mask bit for bit, and how long each takes.

    python -m tools.visibility_identity --checkpoint model/odg_cpu.pt --limit 8 \
        --data city-quiet=data/held_out/city-quiet/infos_all.pkl \
        open-road=data/held_out/open-road/infos_all.pkl [--against main]

For each split, its first --limit keyframes in order go through the node's online step (its
settings: shipped precision, padding, calibration); the inputs of its visibility (the
predicted labels, the hazard, the current set's geometry) are kept, and both visibilities
compute the observed mask from them: it must be the same voxel for voxel. Then both are
timed on those inputs, taking turns, one thread (medians; CPU time). Exits 1 where a mask
differs.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch
from tqdm import tqdm

from tools.revision import module_at, report


def visibility_inputs(model, cfg, infos: str, limit: int) -> list:
    """(args, kwargs) of the step's visibility call on the first ``limit`` keyframes."""
    from odg_ros.bench.step_timing import node_predictor, node_settings
    from odg_ros.data.dataset import OccDataset
    from odg_ros.preprocess import image_bounds
    dataset = OccDataset(infos, cfg)
    predictor = node_predictor(model, cfg, "cpu", node_settings())
    captured = []

    def keep(_module, args, kwargs):
        captured.append(([a.clone() for a in args],
                         {k: v.clone() for k, v in kwargs.items() if v is not None}))
    handle = predictor.online_step.visibility.register_forward_pre_hook(keep, with_kwargs=True)
    try:
        for info in dataset.infos[:limit]:
            names = dataset.camera_names
            ego2img, _, _ = dataset.frame_geometry(info["cams"], np.asarray(info["ego_pose"]))
            bounds = image_bounds([info["cams"][c]["image_hw"] for c in names],
                                  dataset.image_size)
            images = np.stack([dataset.load_image(info["cams"][c]) for c in names])
            predictor.step(images, ego2img, np.asarray(info["ego_pose"]),
                           info["timestamp"] * 1e-6, bounds=bounds)
    finally:
        handle.remove()
    return captured


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", nargs="+", required=True, metavar="NAME=INFOS")
    parser.add_argument("--checkpoint", default="model/odg_cpu.pt")
    parser.add_argument("--limit", type=int, default=8, help="keyframes per split")
    parser.add_argument("--against", default="main", help="git revision (default main)")
    parser.add_argument("--repeats", type=int, default=3, help="timed passes over the inputs")
    args = parser.parse_args(argv)
    from odg_ros.network.checkpoint import load_model
    from odg_ros.network.visibility import Visibility
    torch.set_num_threads(1)
    model, cfg = load_model(args.checkpoint, device="cpu")
    before = module_at(args.against, "odg_ros/network/visibility.py").Visibility
    shape = (cfg.grid_shape, cfg.pc_range, cfg.voxel_size, cfg.num_classes)
    new, old = Visibility(*shape), before(*shape)
    result, seconds = {"against": args.against, "splits": {}}, {"old": [], "new": []}
    with torch.inference_mode():
        for item in args.data:
            name, infos = item.split("=", 1)
            inputs = visibility_inputs(model, cfg, infos, args.limit)
            same = [torch.equal(new(*a, **k), old(*a, **k)) for a, k in inputs]
            observed = sum(int(new(*a, **k).sum()) for a, k in inputs)
            result["splits"][name] = {"keyframes": len(same), "identical": sum(same),
                                      "observed_voxels": observed}
            for _ in tqdm(range(args.repeats), desc=f"timing {name}"):
                for a, k in inputs:
                    for label, visibility in (("old", old), ("new", new)):
                        start = time.process_time()
                        visibility(*a, **k)
                        seconds[label].append(time.process_time() - start)
    ratios = [n / o for n, o in zip(seconds["new"], seconds["old"])]
    result.update({f"{k}_ms_median": round(1e3 * statistics.median(v), 2)
                   for k, v in seconds.items()})
    result["new_over_old_median"] = round(statistics.median(ratios), 3)
    differ = [n for n, r in result["splits"].items() if r["identical"] != r["keyframes"]]
    return report(result, differ and f"visibility_identity: the observed mask differs in {differ}")


if __name__ == "__main__":
    sys.exit(main())
