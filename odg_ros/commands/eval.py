"""``odg eval --checkpoint CKPT --data INFOS [--save-pred DIR] [--miou-convention C]
[--query-budget full|auto|FRACTION] [--json]``.

The grid is padded as OPUS pads it at test time (``network/padding.py``) unless
``--set occupancy_padding=false``."""
from __future__ import annotations

import json
import sys

from ..metrics.detection import format_detection
from ..metrics.score import format_table
from ..network.checkpoint import load_model
from ..network.precision import resolve_device
from ..online.predictor import resolve_budget
from ..train.evaluate import evaluate
from .common import (add_device_option, add_json_option, add_set_option, config_overrides,
                     existing_dir, existing_file, infos_file, positive_int)
from .score import add_miou_convention


def add_arguments(parser):
    parser.add_argument("--checkpoint", required=True, type=existing_file,
                        help="checkpoint file (odg train / odg export; model/odg_cpu.pt ships)")
    parser.add_argument("--data", required=True, type=infos_file,
                        help="infos of the split to evaluate (odg prepare)")
    parser.add_argument("--occ-root", type=existing_dir, default=None,
                        help="GT root (default: the infos' occ_root, else <dataroot>/gts)")
    parser.add_argument("--save-pred", default=None,
                        help="write <token>.npz predictions here (what odg score --pred reads; "
                             "default: not saved)")
    add_device_option(parser)
    parser.add_argument("--limit", type=positive_int, default=None,
                        help="the first N samples only (default: all)")
    parser.add_argument("--no-rayiou", action="store_true", help="skip RayIoU (faster)")
    add_miou_convention(parser)
    parser.add_argument("--query-budget", default="full", metavar="full|auto|FRACTION",
                        help="the queries the later decoder layers refine, as the node's "
                             "query_budget parameter: full (default), auto (chosen per "
                             "keyframe from the one before) or a fraction in (0, 1]; the "
                             "result then says the mean share of the queries refined")
    add_json_option(parser)
    add_set_option(parser, help="config override at inference, e.g. motion_compensation=false "
                             "(what a trained model loses without a component) or "
                             "score_threshold=0.3 (default: the checkpoint's config)")


def run(args) -> int:
    device = resolve_device(args.device)
    model, cfg = load_model(args.checkpoint, device=device, **config_overrides(args.set))
    budgets, policy = resolve_budget(args.query_budget, model, cfg)
    budget = policy if policy is not None else budgets[0]
    options = dict(occ_root=args.occ_root, device=device, rayiou=not args.no_rayiou,
                   limit=args.limit, progress=not args.json,
                   miou_convention=args.miou_convention)
    result = evaluate(model, cfg, args.data, save_pred=args.save_pred, budget=budget, **options)
    if budget is not None:      # the same keyframes with every query refined, for the change
        full = evaluate(model, cfg, args.data, **options)
        result["query_budget"]["against_full"] = against_full(result, full)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(format_table(result))
        print(f"grid padding (OPUS test time): {'on' if cfg.occupancy_padding else 'off'}")
        print(f"mIoU over the dynamic classes: {result['mIoU_dynamic']}")
        if "boxes" in result:
            print(format_detection(result["boxes"]))
        if "query_budget" in result:
            print(format_budget_use(result["query_budget"]))
    if args.save_pred:          # stderr: --json keeps stdout for the JSON
        saved = result["predictions"]
        print(f"odg eval: wrote {saved['files']} predictions (<token>.npz, for odg score "
              f"--pred) to {saved['folder']}", file=sys.stderr)
    return 0


COMPARED = ("mIoU", "mIoU_dynamic", "RayIoU", "IoU_geometry")


def against_full(result: dict, full: dict) -> dict:
    """{metric: {"full": its value with every query refined, "change": result's minus it}}
    for the scores both runs have (percent; boxes: their mAP)."""
    pairs = [(k, result.get(k), full.get(k)) for k in COMPARED]
    if "boxes" in result and "boxes" in full:
        pairs.append(("box mAP", result["boxes"]["mAP"], full["boxes"]["mAP"]))
    return {k: {"full": f, "change": round(r - f, 2)} for k, r, f in pairs
            if r is not None and f is not None}


def format_budget_use(use: dict) -> str:
    """The budgets that ran, in words, with their keyframes, and the change against full."""
    lines = [f"query budget {use['mode']}: on average {100 * use['mean_refined_fraction']:.1f} "
             "% of the queries refined by the later decoder layers; keyframes per budget:"]
    lines += [f"  {count:4d}  {use['budgets'][name]}"
              for name, count in use["keyframes_per_budget"].items()]
    change = use.get("against_full")
    if change:
        lines.append("against full (every query refined, the same keyframes in this run): "
                     + ", ".join(f"{k} {c['full'] + c['change']:.2f} ({c['change']:+.2f})"
                                 for k, c in change.items()))
    return "\n".join(lines)
