"""How well the node's visibility (free / occupied / unknown) agrees with the world's own
``mask_camera`` over held-out keyframes, and what it costs.

    python -m tools.visibility_agreement --data data/held_out/city-dense/infos_all.pkl
    python -m tools.visibility_agreement --data data/held_out/city-dense/infos_all.pkl \
        --checkpoint model/odg_cpu.pt
    python -m tools.visibility_agreement --data data/held_out/city-dense/infos_all.pkl \
        --device cuda
    python -m tools.visibility_agreement --data data/held_out/city-dense/infos_all.pkl \
        --checkpoint model/odg_cpu.pt --step-share 12

Without --checkpoint the visibility is computed from the ground-truth occupancy (what the
method can reach when the grid is right; the predicted surfaces alone), on --device, and
timed there (the median per keyframe: CPU time of one thread on the CPU, CUDA events on a
GPU); with it, from the grid the node's online step predicts on the CPU (keyframes in scene
order, history as in the node; the checkpoint's hazard and --min-clear as the node's
visibility_min_clear). Prints one line per scene and a JSON summary (over all voxels of all
keyframes: IoU, precision and recall of "observed"; the mean IoU per keyframe).

--step-share N times the node's online step (its settings: precision, padding, visibility) on
the first N keyframes of the first scene, one thread: the padding's and the visibility's
shares of its CPU time by the step's marks and by the step without each, set by set
interleaved (medians;
odg_ros/bench/stage_shares.py, the numbers tools/node_rate.py and odg bench --shares
report), and the calibration's share by its marks.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
from tqdm import tqdm

from odg_ros.model_config import load_preset
from odg_ros.data.dataset import OccDataset
from odg_ros.network.visibility import DEFAULT_MIN_CLEAR, Visibility, image_bounds


def keyframe_inputs(dataset: OccDataset, index: int):
    """(ego2img [N, 4, 4], the camera images' bounds in network-input pixels [N, 4],
    mask_camera, semantics) of one keyframe."""
    info = dataset.infos[index]
    ego2img, _, _ = dataset.frame_geometry(info["cams"], np.asarray(info["ego_pose"]))
    bounds = image_bounds([info["cams"][c]["image_hw"] for c in dataset.camera_names],
                          dataset.image_size)
    semantics, _, mask_camera, _ = dataset.load_occupancy(info)
    return ego2img, bounds, mask_camera.astype(bool), semantics


def timed(visibility, device, semantics, ego2img, bounds):
    """(observed uint8 [X*Y*Z], seconds it took on ``device``)."""
    inputs = (torch.from_numpy(semantics.reshape(-1)),
              torch.tensor(ego2img, dtype=torch.float32),
              torch.tensor(np.linalg.inv(ego2img), dtype=torch.float32),
              torch.tensor(bounds, dtype=torch.float32))
    inputs = [t.to(device) for t in inputs]
    with torch.inference_mode():
        if device.type != "cuda":
            start = time.process_time()
            observed = visibility(*inputs)
            return observed.numpy(), time.process_time() - start
        visibility(*inputs)                                  # warm-up (allocator, kernels)
        begin, end = (torch.cuda.Event(enable_timing=True) for _ in range(2))
        begin.record()
        observed = visibility(*inputs)
        end.record()
        end.synchronize()
        return observed.cpu().numpy(), begin.elapsed_time(end) / 1e3


def predicted_observed(checkpoint: str, dataset: OccDataset, progress: bool, min_clear: float):
    """observed bool [X, Y, Z] per keyframe from the online step's predicted grid."""
    from odg_ros.network.checkpoint import load_model
    from odg_ros.online.predictor import OnlinePredictor
    model, cfg = load_model(checkpoint, device="cpu")
    predictor, scene = None, None
    for index in tqdm(range(len(dataset)), desc="online step", disable=not progress):
        info = dataset.infos[index]
        if info["scene_token"] != scene:
            predictor = OnlinePredictor(model, cfg, "cpu", min_clear=min_clear)
            scene = info["scene_token"]
        ego2img, bounds, _, _ = keyframe_inputs(dataset, index)
        images = np.stack([dataset.load_image(info["cams"][c]) for c in dataset.camera_names])
        prediction = predictor.step(images, ego2img, np.asarray(info["ego_pose"]),
                                    info["timestamp"] * 1e-6, bounds=bounds)
        yield prediction.observed


def step_share(checkpoint: str, infos: str, sets: int) -> dict:
    """The padding's and the visibility's shares of the node's CPU step (its settings, one
    thread) over the first ``sets`` keyframes of the first scene: by the step's marks and by
    the step without each (odg_ros/bench/stage_shares.py, what tools/node_rate.py and odg
    bench --shares report), and the calibration's by its marks."""
    from odg_ros.bench.stage_shares import stage_shares
    from odg_ros.bench.step_timing import data_camera_sets, node_settings
    from odg_ros.network.checkpoint import load_model
    model, cfg = load_model(checkpoint, device="cpu")
    result = stage_shares(model, cfg, data_camera_sets(infos, cfg, sets), node_settings(),
                          threads=1)
    calibration = result["stage_cpu_ms"].get("calibration")
    return {**result, "calibrated": cfg.calibration is not None,
            "calibration_share_by_marks": None if calibration is None else
            round(calibration / result["marked_step_cpu_ms"], 4)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="infos file of held-out keyframes")
    parser.add_argument("--checkpoint", default=None,
                        help="predict the grid with this checkpoint (default: use the "
                             "ground-truth occupancy)")
    parser.add_argument("--preset", default="odg_cpu", help="grid and image size (GT mode)")
    parser.add_argument("--limit", type=int, default=None, help="first N keyframes only")
    parser.add_argument("--device", default="cpu",
                        help="where the visibility of the ground truth runs and is timed")
    parser.add_argument("--step-share", type=int, default=0, metavar="N",
                        help="with --checkpoint: instead, the padding's, the visibility's "
                             "and the calibration's shares of the node's CPU step on the "
                             "first N keyframes of the first scene")
    parser.add_argument("--min-clear", type=float, default=DEFAULT_MIN_CLEAR,
                        help="with --checkpoint: the node's visibility_min_clear (default "
                             f"{DEFAULT_MIN_CLEAR})")
    args = parser.parse_args(argv)
    if args.step_share and (not args.checkpoint or args.min_clear != DEFAULT_MIN_CLEAR):
        parser.error("--step-share times the node's step: it needs --checkpoint, at the "
                     "node's default --min-clear")
    torch.set_num_threads(1)
    cfg = load_preset(args.preset)
    if args.checkpoint:
        from odg_ros.network.checkpoint import load_model
        cfg = load_model(args.checkpoint, device="cpu")[1]
    dataset = OccDataset(args.data, cfg)
    if args.limit:
        dataset.infos = dataset.infos[:args.limit]
    if args.step_share:
        print(json.dumps(step_share(args.checkpoint, args.data, args.step_share), indent=2))
        return 0
    device = torch.device(args.device)
    visibility = Visibility(cfg.grid_shape, cfg.pc_range, cfg.voxel_size, cfg.num_classes,
                            device=device)
    predicted = predicted_observed(args.checkpoint, dataset, True, args.min_clear) \
        if args.checkpoint else None
    totals, per_keyframe, per_scene, seconds = np.zeros(4), [], {}, []
    for index in tqdm(range(len(dataset)), desc="keyframes", disable=predicted is not None):
        ego2img, bounds, mask, semantics = keyframe_inputs(dataset, index)
        if predicted is None:
            observed, elapsed = timed(visibility, device, semantics, ego2img, bounds)
            seconds.append(elapsed)
            observed = observed.reshape(mask.shape).astype(bool)
        else:
            observed = next(predicted).astype(bool)
        counts = np.array([(observed & mask).sum(), (observed | mask).sum()])
        totals += [*counts, (observed & ~mask).sum(), (~observed & mask).sum()]
        per_keyframe.append(counts[0] / max(counts[1], 1))
        name = dataset.infos[index]["scene_name"]
        per_scene.setdefault(name, np.zeros(2))
        per_scene[name] += counts
    for name, (inter, union) in per_scene.items():
        print(f"{name}: IoU of observed {inter / union:.4f}")
    summary = {"data": args.data, "grid": "predicted by " + args.checkpoint
               if args.checkpoint else "ground truth", "keyframes": len(per_keyframe),
               "iou_observed": round(float(totals[0] / totals[1]), 4),
               "precision_observed": round(float(totals[0] / (totals[0] + totals[2])), 4),
               "recall_observed": round(float(totals[0] / (totals[0] + totals[3])), 4),
               "mean_keyframe_iou": round(float(np.mean(per_keyframe)), 4),
               # of the voxels said observed, hidden in truth; of those seen, said unknown
               "observed_but_hidden": round(float(totals[2] / (totals[0] + totals[2])), 4),
               "seen_but_unknown": round(float(totals[3] / (totals[0] + totals[3])), 4)}
    if seconds:
        where = "cpu_1_thread" if device.type == "cpu" else device.type
        summary[f"visibility_ms_median_{where}"] = round(1e3 * float(np.median(seconds)), 2)
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
