"""``odg export --checkpoint CKPT --out FILE [--compress int8] [--calibrate INFOS ...]
[--keep-thresholds]``: turn a training checkpoint into a shipped one (weights only,
compressed, thresholds chosen, its confidence, hazard and box scores calibrated as
probabilities on training keyframes; network/calibration.py).
``odg export --checkpoint CKPT --onnx FILE [--frames K]``: the node's online step as ONNX
with named inputs (images, camera matrices, ego warps, time deltas, the history of
features; for onnxruntime or a TensorRT engine; docs/compiled_node.md), fed by
odg_ros/online/onnx_inputs.py.
``odg export --checkpoint CKPT --aoti FILE.pt2 [--device D] [--precision P] [--frames K]``:
the online step compiled ahead of time (AOTInductor) for the node's ``compiled_step``."""
from __future__ import annotations

import json
from pathlib import Path

from ..network.checkpoint import (compress_state, load_model, load_weights, read_checkpoint,
                                  save_checkpoint)
from ..network.precision import NODE_PRECISIONS, resolve_device, resolve_precision
from ..network.visibility import DEFAULT_MIN_CLEAR
from ..train.calibrate import DEFAULT_THRESHOLDS, calibrate_thresholds, fit_probabilities
from .common import (UserError, add_device_option, existing_file, infos_file, positive_int,
                     probability)


def add_arguments(parser):
    parser.add_argument("--checkpoint", required=True, type=existing_file,
                        help="training checkpoint (odg train)")
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--out", default=None,
                      help="the shipped checkpoint to write (no default: this or --onnx)")
    what.add_argument("--onnx", default=None, metavar="FILE",
                      help="write the online step (backbone, history, decoder, "
                           "post-processing, visibility) as ONNX with named inputs instead; "
                           "odg_ros/online/onnx_inputs.py makes them from CameraInfo, "
                           "extrinsics, poses and stamps (no default: this or --out)")
    what.add_argument("--aoti", default=None, metavar="FILE.pt2",
                      help="compile the online step ahead of time (AOTInductor) into this "
                           "file, for the node's compiled_step: a restart then skips the "
                           "compile (no default: this, --out or --onnx)")
    add_device_option(parser, default="cpu",
                      help="--aoti: the device it runs on (cpu, cuda, cuda:N or auto)")
    parser.add_argument("--precision", choices=NODE_PRECISIONS, default="auto",
                        help="--aoti: the node's precision parameter (default auto, as the "
                             "node's: bf16-encoder on a CPU with bf16 instructions, else fp32; "
                             "resolved on this machine)")
    parser.add_argument("--frames", type=positive_int, default=None,
                        help="--aoti, --onnx: the history frames, the node's "
                             "history_frames (default: the model's)")
    parser.add_argument("--visibility-min-clear", type=probability, default=DEFAULT_MIN_CLEAR,
                        help="--aoti, --onnx: the node's visibility_min_clear (default "
                             f"{DEFAULT_MIN_CLEAR})")
    parser.add_argument("--compress", choices=("none", "fp16", "int8"), default="int8",
                        help="weight storage (int8: per-output-channel scales, ~4x smaller)")
    parser.add_argument("--calibrate", default=None, metavar="INFOS", type=infos_file,
                        nargs="+",
                        help="training keyframes (never a held-out split) to choose "
                             "score_threshold by mIoU and box_score_threshold by F1 on (the "
                             "first file), and to fit the confidence, the visibility's hazard "
                             "and the box scores as probabilities on (every file); default: "
                             "keep the checkpoint's")
    parser.add_argument("--keep-thresholds", action="store_true",
                        help="with --calibrate: fit the probabilities only and keep the "
                             "checkpoint's thresholds, so its grid stays the same")
    parser.add_argument("--limit", type=positive_int, default=None,
                        help="calibration keyframes of each --calibrate file (default: all)")
    parser.add_argument("--thresholds", type=float, nargs="+", default=list(DEFAULT_THRESHOLDS),
                        help="score thresholds tried by --calibrate")


def run(args) -> int:
    if args.onnx:
        return export_step(args)
    if args.aoti:
        return export_compiled_step(args)
    if args.keep_thresholds and not args.calibrate:
        raise UserError("--keep-thresholds needs --calibrate (it keeps the thresholds while "
                        "the probabilities are fitted)")
    compress = None if args.compress == "none" else args.compress
    model, cfg = load_model(args.checkpoint)
    stored = read_checkpoint(args.checkpoint)
    # weights stored as they are when already compressed this way (bit for bit: compressing
    # decompressed int8 weights again need not give the same bytes)
    state = stored["model"] if stored.get("compression") == compress else None
    report = {"source": str(args.checkpoint), "compression": compress}
    if args.calibrate:
        # Calibrate the weights as shipped: compression first, then the threshold on them.
        load_weights(model, compress_state(model.state_dict(), compress) if state is None
                     else state)
        if not args.keep_thresholds:
            found = calibrate_thresholds(model, cfg, args.calibrate[0], args.thresholds,
                                         limit=args.limit)
            cfg = cfg.replace(score_threshold=found["best"])
            if found["box"] is not None:
                cfg = cfg.replace(box_score_threshold=found["box"]["threshold"])
            report.update(calibration=str(args.calibrate[0]),
                          calibration_samples=found["samples"],
                          mIoU_by_threshold=found["mIoU"], box_f1=found["box"])
        fitted = fit_probabilities(model, cfg, args.calibrate, limit=args.limit)
        cfg = cfg.replace(calibration=fitted["calibration"])
        model.cfg = cfg
        report.update(probabilities=[str(p) for p in args.calibrate], fitted=fitted["report"])
    report["score_threshold"] = cfg.score_threshold
    report["box_score_threshold"] = cfg.box_score_threshold
    # what else the source recorded (how its heads were trained, its earlier export) stays
    extra = {k: v for k, v in stored.items() if k not in ("config", "model", "compression")}
    if "export" in extra:
        report["earlier_export"] = extra["export"]
    extra["export"] = report
    save_checkpoint(args.out, model, extra=extra, compress=compress, state=state)
    report["bytes"] = Path(args.out).stat().st_size
    print(json.dumps({k: v for k, v in report.items() if k != "earlier_export"}, indent=2))
    return 0


def export_step(args) -> int:
    try:
        import onnxscript  # noqa: F401  (torch.onnx's exporter)
    except ImportError:
        print("odg export --onnx needs onnx and onnxscript: pip install onnx onnxscript")
        return 2
    from ..online.onnx_export import export_onnx, graph_signature
    model, cfg = load_model(args.checkpoint)
    frames = args.frames or cfg.num_frames
    if frames > cfg.num_frames:
        raise UserError(f"--frames {frames}: the model takes at most {cfg.num_frames}")
    _, _, files = export_onnx(model, cfg, args.onnx, frames,
                              min_clear=args.visibility_min_clear)
    report = {"source": str(args.checkpoint), "onnx": str(files[0][0]),
              "files": {str(p): size for p, size in files},
              "bytes": sum(size for _, size in files), "history_frames": frames,
              **graph_signature(files[0][0]),
              "inputs_from": "odg_ros/online/onnx_inputs.py (docs/compiled_node.md)"}
    print(json.dumps(report, indent=2))
    return 0


def export_compiled_step(args) -> int:
    import time

    from ..online.artifact import export_artifact
    model, cfg = load_model(args.checkpoint)
    frames = args.frames or cfg.num_frames
    if not args.aoti.endswith(".pt2") or frames > cfg.num_frames:
        raise UserError(f"--aoti {args.aoti} --frames {frames}: a .pt2 file and at most the "
                        f"model's {cfg.num_frames} frames")
    start = time.perf_counter()
    device = resolve_device(args.device)
    path, signature = export_artifact(model, cfg, args.aoti, frames, device,
                                      resolve_precision(args.precision, device),
                                      min_clear=args.visibility_min_clear)
    report = {"source": str(args.checkpoint), "aoti": str(path),
              "bytes": path.stat().st_size, "compile_s": round(time.perf_counter() - start, 1),
              **{k: v for k, v in signature.items() if k != "config"}}
    print(json.dumps(report, indent=2))
    return 0
