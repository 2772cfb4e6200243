"""``odg eval --checkpoint CKPT --data INFOS [--save-pred DIR] [--json]``."""
from __future__ import annotations

import json

import torch

from ..metrics.detection import format_detection
from ..metrics.score import format_table
from ..network.checkpoint import load_model
from ..train.evaluate import evaluate
from .train import parse_overrides


def add_arguments(parser):
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--data", required=True, help="infos of the split to evaluate")
    parser.add_argument("--occ-root", default=None, help="GT root (default: <dataroot>/gts)")
    parser.add_argument("--save-pred", default=None, help="write <token>.npz predictions here")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--limit", type=int, default=None, help="first N samples only")
    parser.add_argument("--no-rayiou", action="store_true")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="config override at inference, e.g. motion_compensation=false "
                             "(what a trained model loses without a component) or "
                             "score_threshold=0.3")


def run(args) -> int:
    device = ("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" \
        else args.device
    model, cfg = load_model(args.checkpoint, device=device, **parse_overrides(args.set))
    result = evaluate(model, cfg, args.data, occ_root=args.occ_root, save_pred=args.save_pred,
                      device=device, rayiou=not args.no_rayiou, limit=args.limit,
                      progress=not args.json)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(format_table(result))
        print(f"mIoU over the dynamic classes: {result['mIoU_dynamic']}")
        if "boxes" in result:
            print(format_detection(result["boxes"]))
    return 0
