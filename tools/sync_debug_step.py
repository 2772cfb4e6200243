"""One training step's host waits counted three ways, so that the census (what CI pins) can be
checked against CUDA itself:

1. ``torch.cuda.set_sync_debug_mode("warn")``: every CUDA call that makes the host wait for
   the device (a stream synchronisation after a blocking copy, a read of a value or size)
   warns; the warnings of one step are counted, by source line;
2. the census on the GPU (``CensusMode`` with the device type ``cuda``);
3. the census of the same step with the CUDA paths forced, taken on the CPU.

The step is ODG-T's, by default in the configuration CI pins (32 x 88 input, 2 frames, 64
LiDAR pixels per camera, augmentation on, our renderer; ``--image-size 256 704 --frames 8
--render-pixels 512`` is the size users train at), on the first keyframes of ``--data``, after
one warm-up step; every run starts from the same seed. The batch is pinned and uploaded
before the step, as the training loop's prefetcher does. ``--batch-size`` takes several
sizes (one model for all). ``--timed-steps N`` then times N more steps of each batch on the
device (the batch already uploaded: the step without data loading), in seconds per step and
per sample.

    python -m tools.sync_debug_step --data INFOS --backbone-weights R50.pth [--batch-size 1 4]

Prints the counts and the lines that differ, and ``--json`` writes them (a list: one result
per batch size). ``--backbone-weights random``: random weights of the preset's ResNet
(timing and counts only). On a machine without CUDA (``--device cpu``) only the third count
(and the timing, on the CPU) is made.
"""
from __future__ import annotations

import argparse
import collections
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

from odg_ros.model_config import load_preset
from odg_ros.data.batch import collate, to_device
from odg_ros.bench.census import (
    Census,
    CensusMode,
    batch_host_tensors,
    census_of_steps,
    optimizer_host_tensors,
)
from odg_ros.train.trainer import Trainer, TrainOptions
from tools.gpu_tool import parse_args, write_json

PACKAGE = str(Path(__file__).resolve().parents[1] / "odg_ros") + "/"


def trainer_on(device: str, args) -> Trainer:
    torch.manual_seed(0)
    cfg = load_preset(args.preset, image_size=tuple(args.image_size), num_frames=args.frames)
    out_dir = Path(tempfile.mkdtemp())
    weights = args.backbone_weights
    if weights == "random":                    # stands in for pretrained weights: timing only
        from odg_ros.network.backbone import ResNet
        weights = str(out_dir / "random_backbone.pth")
        torch.save(ResNet(cfg.backbone).state_dict(), weights)
    return Trainer(cfg, args.data, TrainOptions(
        out_dir=out_dir, workers=0, progress=False, device=device,
        render_pixels_per_camera=args.render_pixels, backbone_weights=weights,
        augment=True, renderer="torch"))


def seconds_per_step(trainer: Trainer, batch: dict, steps: int) -> float:
    """Wall seconds of one training step on an uploaded batch, over ``steps`` steps."""
    cuda = trainer.device.type == "cuda"
    uploaded = to_device(pinned(batch) if cuda else batch, trainer.device)
    if cuda:
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(steps):
        trainer.train_step(uploaded)
    if cuda:
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / steps


def host_batch(trainer: Trainer, size: int) -> dict:
    dataset = trainer.dataset
    return collate([dataset[i % len(dataset)] for i in range(size)])


def line_of(filename: str, lineno: int) -> str:
    name = filename.removeprefix(PACKAGE)
    return f"{name}:{lineno}"


def census_lines(census: Census) -> dict[str, float]:
    lines = collections.Counter()
    for (_, line), n in census.syncs.items():
        lines[line.split(" ", 1)[0]] += n / census.steps
    return dict(lines)


def pinned(value):
    """A batch's tensors in pinned memory, as the training loader gives them."""
    if torch.is_tensor(value):
        return value.pin_memory()
    if isinstance(value, dict):
        return {k: pinned(v) for k, v in value.items()}
    if isinstance(value, list):
        return [pinned(v) for v in value]
    return value


def counted_on_the_gpu(trainer: Trainer, batch: dict):
    """(sync-debug warnings, their lines, the census on the GPU) of one step, after a
    warm-up step; the batch uploaded first, as the prefetcher does."""
    uploaded = to_device(pinned(batch), trainer.device)
    trainer.train_step(uploaded)
    torch.cuda.synchronize()
    torch.manual_seed(1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            trainer.train_step(uploaded)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    torch.cuda.synchronize()
    waits = [w for w in caught if "synchroniz" in str(w.message)]
    lines = collections.Counter(line_of(w.filename, w.lineno) for w in waits)
    torch.manual_seed(1)
    census = Census()
    with CensusMode(census, "cuda", batch_host_tensors(uploaded)
                    + optimizer_host_tensors(trainer.optimizer)):
        trainer.train_step(uploaded)
    torch.cuda.synchronize()
    return len(waits), dict(lines), census


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="training infos (odg prepare)")
    parser.add_argument("--backbone-weights", required=True,
                        help="ResNet checkpoint, or random (timing and counts only)")
    parser.add_argument("--preset", default="odg_t")
    parser.add_argument("--image-size", type=int, nargs=2, default=(32, 88), metavar=("H", "W"))
    parser.add_argument("--frames", type=int, default=2)
    parser.add_argument("--render-pixels", type=int, default=64)
    parser.add_argument("--batch-size", type=int, nargs="+", default=[1],
                        help="one or more batch sizes (default: 1)")
    parser.add_argument("--timed-steps", type=int, default=0,
                        help="then time this many steps of each batch (default: none)")
    parser.add_argument("--device", default="cuda", choices=("cuda", "cpu"))
    parser.add_argument("--no-cpu-census", action="store_true",
                        help="leave out the census with the CUDA paths on the CPU (minutes at "
                             "batch 4; CI pins it)")
    args = parse_args(parser, argv, "sync_debug_step", "--device cpu counts the census only",
                      json_help="also write the counts here")
    if args is None:
        return 2
    results = []
    trainers = {}
    if args.device == "cuda":
        trainers["cuda"] = trainer_on("cuda", args)
    if not args.no_cpu_census or args.device == "cpu":
        trainers["cpu"] = trainer_on("cpu", args)
    for size in args.batch_size:
        results.append(counted(trainers, size, args))
        write_json(args.json, results)            # each batch's result as soon as it is made
    return 0


def counted(trainers: dict, size: int, args) -> dict:
    """The counts (and the timing) of one batch size."""
    start = time.time()
    result = {"preset": args.preset, "image_size": list(args.image_size),
              "frames": args.frames, "batch_size": size, "render_pixels": args.render_pixels}
    if "cuda" in trainers:
        trainer = trainers["cuda"]
        batch = host_batch(trainer, size)
        warned, warned_lines, gpu_census = counted_on_the_gpu(trainer, batch)
        result.update(sync_debug_waits=warned, sync_debug_lines=warned_lines,
                      census_cuda_waits=gpu_census.per_step(gpu_census.syncs),
                      census_cuda_lines=census_lines(gpu_census))
        if args.timed_steps:
            seconds = seconds_per_step(trainer, batch, args.timed_steps)
            result.update(device=torch.cuda.get_device_name(), seconds_per_step=seconds,
                          seconds_per_sample=seconds / size)
    if "cpu" in trainers:
        trainer = trainers["cpu"]
        batch = host_batch(trainer, size)
        torch.manual_seed(1)
        census = census_of_steps(trainer, [batch, batch], cuda_paths=True)
        result.update(census_cuda_paths_waits=census.per_step(census.syncs),
                      census_cuda_paths_kinds=census.waits_by_kind(),
                      census_cuda_paths_ops=census.per_step(census.ops),
                      census_cuda_paths_lines=census_lines(census))
        if args.timed_steps and "cuda" not in trainers:
            seconds = seconds_per_step(trainer, batch, args.timed_steps)
            result.update(device="cpu", seconds_per_step=seconds,
                          seconds_per_sample=seconds / size)
    result["seconds"] = round(time.time() - start, 1)
    print(f"batch {size}:")
    for key in ("sync_debug_waits", "census_cuda_waits", "census_cuda_paths_waits",
                "seconds_per_step", "seconds_per_sample"):
        if key in result:
            print(f"  {key}: {result[key]:g}")
    for key in ("sync_debug_lines", "census_cuda_lines", "census_cuda_paths_lines"):
        if key in result:
            print(f"  {key}: {json.dumps(result[key], sort_keys=True)}")
    return result


if __name__ == "__main__":
    sys.exit(main())
