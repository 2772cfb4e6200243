"""Score a perturbed prediction with ``odg score`` and with the scalar transcription of
SparseOcc's RayIoU (testing/sparseocc_reference.py), and print both.

    python -m tools.rayiou_against_sparseocc --data INFOS.pkl [--out DIR] [--seed 0]

The prediction of every keyframe with GT is its GT shifted one voxel along +x with 3 % of the
voxels relabelled at random (labels 0..17). The transcription casts ray by ray in pure Python:
about a minute per keyframe on one CPU core.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from odg_ros.commands.score import score_split
from odg_ros.data.occ_io import load_occ
from odg_ros.metrics.score import load_scoring_infos, resolve_occ_root
from testing.sparseocc_reference import sparseocc_origins, sparseocc_rayiou


def perturbed(gt: np.ndarray, rng, free: int) -> np.ndarray:
    pred = np.full_like(gt, free)
    pred[1:] = gt[:-1]
    relabel = rng.random(gt.shape) < 0.03
    pred[relabel] = rng.integers(0, free + 1, int(relabel.sum()))
    return pred


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, type=Path, help="infos pickle (odg prepare)")
    parser.add_argument("--out", type=Path, default=None, help="prediction folder (default: tmp)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    meta = load_scoring_infos(args.data)
    infos, root = meta["infos"], resolve_occ_root(meta)
    free = 17 if meta["dataset"] == "nuscenes" else 15
    out = Path(args.out or tempfile.mkdtemp(prefix="rayiou_check_"))
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    preds, gts, origins = [], [], []
    for i, info in enumerate(infos):
        if not info["occ_path"]:
            continue
        gt = load_occ(root / info["occ_path"], meta["dataset"])[0]
        pred = perturbed(gt, rng, free)
        np.savez_compressed(out / f"{info['token']}.npz", semantics=pred)
        scene = sorted((j for j, o in enumerate(infos) if o["scene_token"] == info["scene_token"]),
                       key=lambda j: infos[j]["timestamp"])
        frames = [(infos[j]["ego_pose"], infos[j]["lidar2ego"]) for j in scene]
        preds.append(pred)
        gts.append(gt)
        origins.append(sparseocc_origins(frames, scene.index(i)))

    ours = score_split(out, args.data)
    _, theirs = sparseocc_rayiou(preds, gts, origins, num_classes=free)
    report = {"keyframes": len(preds), "odg score": {}, "SparseOcc transcription": {},
              "difference": {}}
    for key in ("RayIoU", "RayIoU@1", "RayIoU@2", "RayIoU@4"):
        report["odg score"][key] = round(ours[key], 4)
        report["SparseOcc transcription"][key] = round(100 * theirs[key], 4)
        report["difference"][key] = round(ours[key] - 100 * theirs[key], 6)
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
