"""``odg eval --checkpoint CKPT --data [NAME=]INFOS ... [--save-pred DIR]
[--miou-convention C] [--query-budget full|auto|FRACTION] [--visibility-min-clear P]
[--precision P] [--json]``.

The grid is padded as OPUS pads it at test time (``network/padding.py``) unless
``--set occupancy_padding=false``. Several ``--data`` splits (scene classes) are scored each
and together. Beside mIoU, RayIoU and box mAP: what a planner reads (metrics/planner.py):
the visibility against mask_camera, the confidence's calibration error, label flips."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from ..metrics.detection import format_detection
from ..metrics.planner import format_planner
from ..metrics.score import format_table
from ..network.checkpoint import load_model
from ..network.precision import NODE_PRECISIONS, resolve_device, resolve_precision
from ..network.visibility import DEFAULT_MIN_CLEAR
from ..online.execution import resolve_budget
from ..train.evaluate import BEV_BAND, evaluate
from .common import (UserError, add_device_option, add_json_option, add_set_option,
                     config_overrides, existing_dir, existing_file, infos_file, positive_int,
                     probability)
from .score import add_miou_convention


def add_arguments(parser):
    parser.add_argument("--checkpoint", required=True, type=existing_file,
                        help="checkpoint file (odg train / odg export; model/odg_cpu.pt ships)")
    parser.add_argument("--data", required=True, type=named_infos, nargs="+",
                        metavar="[NAME=]INFOS",
                        help="infos of the split to evaluate (odg prepare); several (scene "
                             "classes, e.g. city-dense=data/held_out/city-dense/infos_all.pkl; "
                             "a plain path is named after its folder) are scored each and "
                             "together")
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
    parser.add_argument("--visibility-min-clear", type=probability, default=DEFAULT_MIN_CLEAR,
                        help="the node's visibility_min_clear: the least probability of a "
                             f"clear ray for a voxel to count as observed (default "
                             f"{DEFAULT_MIN_CLEAR})")
    parser.add_argument("--bev-band", type=float, nargs=2, default=list(BEV_BAND),
                        metavar=("MIN_Z", "MAX_Z"),
                        help="the node's bev_min_z and bev_max_z (m, grid frame; default "
                             f"{BEV_BAND[0]} {BEV_BAND[1]})")
    parser.add_argument("--precision", choices=NODE_PRECISIONS, default=None,
                        help="score the node's arithmetic at this precision (its folded "
                             "backbone; bf16 / fp16 weights and an autocast decoder, or "
                             "bf16-encoder: ResNet + FPN in bf16, the decoder in fp32; auto: "
                             "what the node's precision auto picks on this machine; default: "
                             "the training model in float32)")
    add_json_option(parser)
    add_set_option(parser, help="config override at inference, e.g. motion_compensation=false "
                             "(what a trained model loses without a component) or "
                             "score_threshold=0.3 (default: the checkpoint's config)")


def run(args) -> int:
    device = resolve_device(args.device)
    model, cfg = load_model(args.checkpoint, device=device, **config_overrides(args.set))
    budgets, policy = resolve_budget(args.query_budget, model, cfg)
    budget = policy if policy is not None else budgets[0]
    names = [name for name, _ in args.data]
    if len(set(names)) != len(names):
        raise UserError(f"--data names {names}: give each split its own NAME=")
    data = args.data[0][1] if len(args.data) == 1 else dict(args.data)
    scored = model
    if args.precision is not None:
        from ..online.step import NodeInferenceModel
        args.precision = resolve_precision(args.precision, device)
        scored = NodeInferenceModel(model, cfg, device, args.precision)
    options = dict(occ_root=args.occ_root, device=device, rayiou=not args.no_rayiou,
                   limit=args.limit, progress=not args.json,
                   miou_convention=args.miou_convention, min_clear=args.visibility_min_clear,
                   bev_band=tuple(args.bev_band))
    result = evaluate(scored, cfg, data, save_pred=args.save_pred, budget=budget, **options)
    if budget is not None:      # the same keyframes with every query refined, for the change
        full = evaluate(scored, cfg, data, **options)
        result["query_budget"]["against_full"] = against_full(result, full)
    if args.precision is not None:
        result["precision"] = f"{args.precision} (the node's arithmetic)"
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for name, values in result.get("sets", {}).items():
            print(f"{name}: mIoU {_number(values['mIoU'])}, RayIoU "
                  f"{_number(values.get('RayIoU'))}, {values['samples']} keyframes")
        print(format_table(result))
        print(f"grid padding (OPUS test time): {'on' if cfg.occupancy_padding else 'off'}")
        if args.precision is not None:
            print(f"precision: {result['precision']}")
        print(f"mIoU over the dynamic classes: {result['mIoU_dynamic']}")
        if "boxes" in result:
            print(format_detection(result["boxes"]))
        if "query_budget" in result:
            print(format_budget_use(result["query_budget"]))
        print(format_planner(result))
    if args.save_pred:          # stderr: --json keeps stdout for the JSON
        saved = result["predictions"]
        print(f"odg eval: wrote {saved['files']} predictions (<token>.npz, for odg score "
              f"--pred) to {saved['folder']}", file=sys.stderr)
    return 0


def _number(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def named_infos(text: str) -> tuple[str, str]:
    """[NAME=]INFOS -> (name, path); a plain path is named after its folder."""
    name, _, path = text.rpartition("=") if "=" in text else ("", "", text)
    path = infos_file(path)
    return name or Path(path).resolve().parent.name, path


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
