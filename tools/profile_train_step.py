"""Where a training step's host time goes: ATen calls per step, and the places that read a
tensor's value on the host (on CUDA each such read waits for the GPU queue to drain).

    python tools/profile_train_step.py --preset odg_cpu --data out/gpu_world/infos_all.pkl \
        [--device cpu|cuda] [--steps 2]

The numbers in docs/reports/2026-11-25-h100.md ("Training speed") come from this on the CPU. Reads of
CPU tensors are counted on a CPU only: on CUDA they cost no synchronisation (the optimizer's
step counters, say).
"""
from __future__ import annotations

import argparse
import collections
import tempfile
import time
import traceback
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from odg_ros.config import load_preset
from odg_ros.data.batch import collate
from odg_ros.train.trainer import Trainer, TrainOptions

HOST_READS = ("item", "__bool__", "__int__", "__float__", "tolist", "numpy")


def call_site() -> str:
    """The innermost odg_ros frame that asked for the value."""
    for frame in reversed(traceback.extract_stack()[:-2]):
        if "/odg_ros/" in frame.filename:
            return f"{frame.filename.split('/odg_ros/')[1]}:{frame.lineno} {frame.line.strip()}"
    return "(outside odg_ros)"


class HostReadCounter:
    """Counts, per call site, the host reads of tensors on ``device_type`` while active."""

    def __init__(self, device_type: str):
        self.device_type, self.sites = device_type, collections.Counter()
        self._originals = {name: getattr(torch.Tensor, name) for name in HOST_READS}

    def __enter__(self):
        for name, original in self._originals.items():
            def counted(tensor, *args, _original=original, _name=name, **kwargs):
                if tensor.device.type == self.device_type:
                    self.sites[f"{_name:8s} {call_site()}"] += 1
                return _original(tensor, *args, **kwargs)
            setattr(torch.Tensor, name, counted)
        return self

    def __exit__(self, *exc):
        for name, original in self._originals.items():
            setattr(torch.Tensor, name, original)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="odg_cpu")
    parser.add_argument("--data", required=True, help="infos pickle (odg prepare)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--steps", type=int, default=2)
    parser.add_argument("--top", type=int, default=15, help="call sites to list")
    args = parser.parse_args(argv)
    trainer = Trainer(load_preset(args.preset), args.data, TrainOptions(
        out_dir=Path(tempfile.mkdtemp()), epochs=1, workers=0, progress=False,
        device=args.device))
    batches = [collate([trainer.dataset[i % len(trainer.dataset)]])
               for i in range(args.steps + 1)]
    trainer.train_step(batches[0])      # warm-up: allocator, lazy inits
    with HostReadCounter(trainer.device.type) as reads, profile(
            activities=[ProfilerActivity.CPU]) as prof:
        start = time.perf_counter()
        for batch in batches[1:]:
            trainer.train_step(batch)
        seconds = time.perf_counter() - start
    calls = sum(event.count for event in prof.key_averages())
    print(f"{args.preset} on {trainer.device}: {seconds / args.steps:.2f} s/step (profiled), "
          f"{calls / args.steps:,.0f} ATen calls/step, "
          f"{sum(reads.sites.values()) / args.steps:,.0f} host reads/step")
    for site, count in reads.sites.most_common(args.top):
        print(f"{count / args.steps:8.0f}  {site}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
