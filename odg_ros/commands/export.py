"""``odg export --checkpoint CKPT --out FILE [--compress int8] [--calibrate INFOS]``:
turn a training checkpoint into a shipped one (weights only, compressed, threshold chosen).
``odg export --checkpoint CKPT --onnx FILE [--frames K]``: the node's online step as ONNX
with named inputs (images, camera matrices, ego warps, time deltas, the history of
features; for onnxruntime or a TensorRT engine; docs/compiled_node.md), fed by
odg_ros/online/onnx_inputs.py.
``odg export --checkpoint CKPT --aoti FILE.pt2 [--device D] [--precision P] [--frames K]``:
the online step compiled ahead of time (AOTInductor) for the node's ``compiled_step``."""
from __future__ import annotations

import json
from pathlib import Path

from ..network.checkpoint import compress_state, load_model, load_weights, save_checkpoint
from ..train.calibrate import DEFAULT_THRESHOLDS, calibrate_thresholds
from ..network.precision import PRECISIONS, resolve_device
from .common import UserError, add_device_option, existing_file, infos_file, positive_int


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
    parser.add_argument("--precision", choices=PRECISIONS, default="fp32",
                        help="--aoti: the node's precision parameter")
    parser.add_argument("--frames", type=positive_int, default=None,
                        help="--aoti, --onnx: the history frames, the node's "
                             "history_frames (default: the model's)")
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
    if args.onnx:
        return export_step(args)
    if args.aoti:
        return export_compiled_step(args)
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
    _, _, files = export_onnx(model, cfg, args.onnx, frames)
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
    path, signature = export_artifact(model, cfg, args.aoti, frames,
                                      resolve_device(args.device), args.precision)
    report = {"source": str(args.checkpoint), "aoti": str(path),
              "bytes": path.stat().st_size, "compile_s": round(time.perf_counter() - start, 1),
              **{k: v for k, v in signature.items() if k != "config"}}
    print(json.dumps(report, indent=2))
    return 0
