"""``odg score``: mIoU, geometry IoU and RayIoU of saved predictions against the Occ3D GT.

    odg score --pred DIR --data INFOS.pkl [--occ-root DIR] [--miou-convention sparseocc|occ3d]
              [--json] [--png FILE]

DIR holds ``<sample_token>.npz`` (key ``semantics``, uint8 200x200x16, labels 0..C with C =
free) for every keyframe of the infos that has GT (``occ_path`` not empty); a missing one is an
error that names it. The GT root is ``--occ-root``, else the infos' ``occ_root`` (relative to
its ``dataroot``), else ``<dataroot>/gts``. The infos' ``dataset`` picks the label set
(nuscenes: 17 classes + free 17; waymo: 15 classes + free 15). Conventions: odg_ros/metrics/.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from tqdm import tqdm

from ..data.occ_io import load_occ
from ..metrics.miou import MIOU_CONVENTIONS
from ..metrics.rayiou import LidarOrigins
from ..metrics.score import (OccScore, format_table, load_scoring_infos, load_prediction,
                             plot_per_class, resolve_occ_root)
from .common import add_json_option


def add_arguments(parser) -> None:
    parser.add_argument("--pred", required=True, type=Path,
                        help="directory of <sample_token>.npz predictions (key 'semantics'), "
                             "as odg eval --save-pred writes them")
    parser.add_argument("--data", required=True, type=Path, help="infos pickle (odg prepare)")
    parser.add_argument("--occ-root", type=Path, default=None,
                        help="GT root the infos' occ_path are relative to (default: the infos' "
                             "occ_root, else <dataroot>/gts)")
    add_miou_convention(parser)
    parser.add_argument("--png", type=Path, default=None,
                        help="also write a per-class bar chart (IoU, RayIoU) to this PNG "
                             "(default: no chart)")
    add_json_option(parser, help="print the scores as JSON (percent, NaN as null) instead of "
                                 "a table")


def add_miou_convention(parser) -> None:
    parser.add_argument("--miou-convention", choices=MIOU_CONVENTIONS, default="sparseocc",
                        help="sparseocc (default; SparseOcc / OPUS): a class absent from the "
                             "GT is left out of the mean; occ3d (Occ3D's Metric_mIoU): it "
                             "counts as IoU 0 where predicted")


def run(args) -> int:
    result = score_split(args.pred, args.data, args.occ_root,     # errors: one line (commands/__init__.py)
                         args.miou_convention)
    if args.png is not None:
        plot_per_class(result, args.png)
        print(f"per-class chart: {args.png}", file=sys.stderr)
    if args.json:
        print(json.dumps(result, indent=2, allow_nan=False))
    else:
        print(format_table(result))
        if result["skipped_no_gt"]:
            print(f"keyframes without GT (not scored): {result['skipped_no_gt']}")
    return 0


def score_split(pred_dir, infos_path, occ_root=None, miou_convention="sparseocc") -> dict:
    """Score every keyframe with GT; returns ``OccScore.result()`` (+ "skipped_no_gt")."""
    meta = load_scoring_infos(infos_path)
    infos, dataset = meta["infos"], meta["dataset"]
    root = resolve_occ_root(meta, occ_root)
    pred_dir = Path(pred_dir)
    if not pred_dir.is_dir():
        raise FileNotFoundError(f"prediction directory not found: {pred_dir}")
    with_gt = [i for i, info in enumerate(infos) if info["occ_path"]]
    if not with_gt:
        raise ValueError(f"{infos_path}: no keyframe has occupancy GT (all occ_path empty)")
    # Check every prediction first: a long run should not die at the last sample.
    missing = [infos[i]["token"] for i in with_gt
               if not (pred_dir / f"{infos[i]['token']}.npz").is_file()]
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise FileNotFoundError(f"{len(missing)} of {len(with_gt)} predictions missing in "
                                f"{pred_dir}: {shown} (expected <sample_token>.npz)")
    origins = LidarOrigins(infos)
    score = OccScore(dataset, miou_convention=miou_convention)
    for i in tqdm(with_gt, desc="odg score", unit="sample", file=sys.stderr):
        gt, _, mask_camera = load_occ(root / infos[i]["occ_path"], dataset)
        pred = load_prediction(pred_dir / f"{infos[i]['token']}.npz", gt.shape,
                               score.free_label)
        score.add(pred, gt, mask_camera, origins(i))
    result = score.result()
    result["skipped_no_gt"] = len(infos) - len(with_gt)
    return result
