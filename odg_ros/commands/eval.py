"""``odg eval --checkpoint CKPT --data INFOS [--save-pred DIR] [--miou-convention C]
[--query-budget full|auto|FRACTION] [--json]``.

The grid is padded as OPUS pads it at test time (``network/padding.py``) unless
``--set occupancy_padding=false``."""
from __future__ import annotations

import json

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
    result = evaluate(model, cfg, args.data, occ_root=args.occ_root, save_pred=args.save_pred,
                      device=device, rayiou=not args.no_rayiou, limit=args.limit,
                      progress=not args.json, miou_convention=args.miou_convention,
                      budget=budget)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(format_table(result))
        print(f"grid padding (OPUS test time): {'on' if cfg.occupancy_padding else 'off'}")
        print(f"mIoU over the dynamic classes: {result['mIoU_dynamic']}")
        if "boxes" in result:
            print(format_detection(result["boxes"]))
        if "query_budget" in result:
            use = result["query_budget"]
            print(f"query budget {use['mode']}: on average "
                  f"{100 * use['mean_refined_fraction']:.1f} % of the queries refined "
                  f"(keyframes per budget: {use['keyframes_per_budget']})")
    return 0
