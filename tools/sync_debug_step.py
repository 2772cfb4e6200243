"""One training step's host waits counted three ways, so that the census (what CI pins) can be
checked against CUDA itself:

1. ``torch.cuda.set_sync_debug_mode("warn")``: every CUDA call that makes the host wait for
   the device (a stream synchronisation after a blocking copy, a read of a value or size)
   warns; the warnings of one step are counted, by source line;
2. the census on the GPU (``CensusMode`` with the device type ``cuda``);
3. the census of the same step with the CUDA paths forced, taken on the CPU.

The step is ODG-T's in the configuration CI pins (32 x 88 input, 2 frames, 64 LiDAR pixels per
camera, augmentation on, our renderer), on the first ``--batch-size`` keyframes of ``--data``,
after one warm-up step; every run starts from the same seed. The batch is pinned and uploaded
before the step, as the training loop's prefetcher does.

    python -m tools.sync_debug_step --data INFOS --backbone-weights R50.pth [--batch-size 4]

Prints the counts and the lines that differ, and ``--json`` writes them. On a machine without
CUDA (``--device cpu``) only the third count is made.
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

from odg_ros.config import load_preset
from odg_ros.data.batch import collate, to_device
from odg_ros.train.census import (
    Census,
    CensusMode,
    batch_host_tensors,
    census_of_steps,
    optimizer_host_tensors,
)
from odg_ros.train.trainer import Trainer, TrainOptions

PACKAGE = str(Path(__file__).resolve().parents[1] / "odg_ros") + "/"


def trainer_on(device: str, args) -> Trainer:
    torch.manual_seed(0)
    cfg = load_preset(args.preset, image_size=tuple(args.image_size), num_frames=args.frames)
    return Trainer(cfg, args.data, TrainOptions(
        out_dir=Path(tempfile.mkdtemp()), workers=0, progress=False, device=device,
        render_pixels_per_camera=args.render_pixels, backbone_weights=args.backbone_weights,
        augment=True, renderer="torch"))


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
    parser.add_argument("--backbone-weights", required=True, help="ResNet checkpoint")
    parser.add_argument("--preset", default="odg_t")
    parser.add_argument("--image-size", type=int, nargs=2, default=(32, 88), metavar=("H", "W"))
    parser.add_argument("--frames", type=int, default=2)
    parser.add_argument("--render-pixels", type=int, default=64)
    parser.add_argument("--batch-size", type=int, default=1)
    parser.add_argument("--device", default="cuda", choices=("cuda", "cpu"))
    parser.add_argument("--no-cpu-census", action="store_true",
                        help="leave out the census with the CUDA paths on the CPU (minutes at "
                             "batch 4; CI pins it)")
    parser.add_argument("--json", help="also write the counts here")
    args = parser.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        print("sync_debug_step: no CUDA device here (--device cpu counts the census only)",
              file=sys.stderr)
        return 2
    start = time.time()
    result = {"preset": args.preset, "image_size": list(args.image_size),
              "frames": args.frames, "batch_size": args.batch_size}
    if args.device == "cuda":
        trainer = trainer_on("cuda", args)
        warned, warned_lines, gpu_census = counted_on_the_gpu(
            trainer, host_batch(trainer, args.batch_size))
        result.update(sync_debug_waits=warned, sync_debug_lines=warned_lines,
                      census_cuda_waits=gpu_census.per_step(gpu_census.syncs),
                      census_cuda_lines=census_lines(gpu_census))
        del trainer
    if not args.no_cpu_census or args.device == "cpu":
        trainer = trainer_on("cpu", args)
        batch = host_batch(trainer, args.batch_size)
        torch.manual_seed(1)
        census = census_of_steps(trainer, [batch, batch], cuda_paths=True)
        result.update(census_cuda_paths_waits=census.per_step(census.syncs),
                      census_cuda_paths_kinds=census.waits_by_kind(),
                      census_cuda_paths_ops=census.per_step(census.ops),
                      census_cuda_paths_lines=census_lines(census))
    result["seconds"] = round(time.time() - start, 1)
    for key in ("sync_debug_waits", "census_cuda_waits", "census_cuda_paths_waits"):
        if key in result:
            print(f"{key}: {result[key]:g}")
    for key in ("sync_debug_lines", "census_cuda_lines", "census_cuda_paths_lines"):
        if key in result:
            print(f"{key}: {json.dumps(result[key], sort_keys=True)}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
