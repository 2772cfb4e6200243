"""``odg export --checkpoint CKPT --out FILE [--compress int8] [--calibrate INFOS]``:
turn a training checkpoint into a shipped one (weights only, compressed, threshold chosen)."""
from __future__ import annotations

import json
from pathlib import Path

from ..network.checkpoint import compress_state, load_model, load_weights, save_checkpoint
from ..train.calibrate import DEFAULT_THRESHOLDS, calibrate_thresholds
from .common import existing_file, infos_file, positive_int


def add_arguments(parser):
    parser.add_argument("--checkpoint", required=True, type=existing_file,
                        help="training checkpoint (odg train)")
    parser.add_argument("--out", required=True, help="the shipped checkpoint to write")
    parser.add_argument("--compress", choices=("none", "fp16", "int8"), default="int8",
                        help="weight storage (int8: per-output-channel scales, ~4x smaller)")
    parser.add_argument("--calibrate", default=None, metavar="INFOS", type=infos_file,
                        help="choose score_threshold by mIoU and box_score_threshold by F1 on "
                             "this split (training keyframes; default: keep the checkpoint's)")
    parser.add_argument("--limit", type=positive_int, default=None,
                        help="calibration keyframes (default: all of --calibrate)")
    parser.add_argument("--thresholds", type=float, nargs="+", default=list(DEFAULT_THRESHOLDS),
                        help="score thresholds tried by --calibrate")


def run(args) -> int:
    compress = None if args.compress == "none" else args.compress
    model, cfg = load_model(args.checkpoint)
    report = {"source": str(args.checkpoint), "compression": compress}
    if args.calibrate:
        # Calibrate the weights as shipped: compression first, then the threshold on them.
        load_weights(model, compress_state(model.state_dict(), compress))
        found = calibrate_thresholds(model, cfg, args.calibrate, args.thresholds,
                                     limit=args.limit)
        cfg = cfg.replace(score_threshold=found["best"])
        if found["box"] is not None:
            cfg = cfg.replace(box_score_threshold=found["box"]["threshold"])
        model.cfg = cfg
        report.update(calibration=str(args.calibrate), calibration_samples=found["samples"],
                      mIoU_by_threshold=found["mIoU"], box_f1=found["box"])
    report["score_threshold"] = cfg.score_threshold
    report["box_score_threshold"] = cfg.box_score_threshold
    save_checkpoint(args.out, model, extra={"export": report}, compress=compress)
    report["bytes"] = Path(args.out).stat().st_size
    print(json.dumps(report, indent=2))
    return 0
