"""`odg train --compile` at a tiny size: seconds to compile (the first step), then steps of
the compiled and the eager trainer interleaved in one process (medians), and how far the
first step's loss terms are apart.

    OMP_NUM_THREADS=1 python -m tools.bench_compile [--backend inductor] [--repeats 5]
        [--fallback-random]

Model: the tests' tiny ODG (ResNet-18, 64 x 176, 2 frames) on their hand-made dataroot, no
augmentation, on this machine's device. --fallback-random makes Inductor draw eager's random
numbers (dropout), so the loss terms can be compared; without it they differ by the dropout
masks. Backends: inductor (what --compile uses), aot_eager or eager (graph capture only).
"""
import argparse
import functools
import statistics
import tempfile
import time
from pathlib import Path

import torch

from testing.helpers import tiny_config, write_tiny_split
from odg_ros.data.batch import collate
from odg_ros.train.trainer import Trainer, TrainOptions


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="inductor")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--fallback-random", action="store_true")
    args = parser.parse_args()
    if args.fallback_random:
        import torch._inductor.config as inductor_config
        inductor_config.fallback_random = True
    real_compile = torch.compile
    torch.compile = functools.partial(real_compile, backend=args.backend)
    split = write_tiny_split(Path(tempfile.mkdtemp()), 2)

    def trainer(compiled):
        torch.manual_seed(0)
        return Trainer(tiny_config(num_frames=2), split, TrainOptions(
            out_dir=Path(tempfile.mkdtemp()), epochs=1, workers=0, warmup_steps=1,
            progress=False, render_pixels_per_camera=64, lr=1e-3, augment=False,
            compile=compiled))
    runs = {"eager": trainer(False), "compiled": trainer(True)}
    batch = collate([runs["eager"].dataset[1]])
    first = {}
    for name, run in runs.items():
        torch.manual_seed(1)
        start = time.perf_counter()
        first[name] = run.train_step(batch).read()[0]
        print(f"{name} first step: {time.perf_counter() - start:.1f} s", flush=True)
    apart = max(abs(first["compiled"][k] - v) / max(abs(v), 1e-9)
                for k, v in first["eager"].items())
    print(f"first step's loss terms: largest relative difference {apart:.2e}")
    times = {name: [] for name in runs}
    for _ in range(args.repeats):
        for name, run in runs.items():
            start = time.perf_counter()
            run.train_step(batch).read()      # the step finishes before the clock stops
            times[name].append(time.perf_counter() - start)
    eager, compiled = (statistics.median(times[n]) for n in ("eager", "compiled"))
    print(f"step, median of {args.repeats}: eager {eager:.2f} s, compiled {compiled:.2f} s "
          f"(compiled / eager {compiled / eager:.2f})")
    stats = torch._dynamo.utils.counters["stats"]
    print(f"graphs: {stats['unique_graphs']}, graph breaks: "
          f"{sum(torch._dynamo.utils.counters['graph_break'].values())}")


if __name__ == "__main__":
    main()
