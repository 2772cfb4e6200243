"""One training step of this code against the whole odg_ros package of an earlier revision,
in one process, interleaved, medians; and whether their loss terms are equal.

    python -m tools.bench_against_revision --data INFOS [--against main] [--preset odg_cpu]
        [--repeats 5] [--no-augment]

Revisions older than the device-side augmentation train without it (compare with
--no-augment), and those older than the uint8 loader take images normalised on the host.

The revision's package is imported under another name, so the two trainers share nothing but
torch. Both are built from the same seed (the same initial weights) and take the same batches
in turn, the alternation reversed every step. Before each step the global random state is
set from the step index, so both draw the same augmentation and dropout: their loss terms
should then be equal, and they are compared term by term. One warm-up step is not timed.
"""
import argparse
import dataclasses
import importlib
import importlib.util
import itertools
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from odg_ros.model_config import load_preset
from odg_ros.preprocess import normalize
from odg_ros.train import trainer as current

ROOT = Path(__file__).resolve().parents[1]
OLD_NAME = "odg_before"


def package_at(rev: str, into: Path):
    """The odg_ros package of ``rev``, importable as OLD_NAME (its imports are relative)."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "odg_ros"],
                             check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    (into / "odg_ros").rename(into / OLD_NAME)
    # the package itself goes into sys.modules; its submodules are then found in its folder
    spec = importlib.util.spec_from_file_location(
        OLD_NAME, into / OLD_NAME / "__init__.py",
        submodule_search_locations=[str(into / OLD_NAME)])
    package = importlib.util.module_from_spec(spec)
    sys.modules[OLD_NAME] = package
    spec.loader.exec_module(package)
    return importlib.import_module(f"{OLD_NAME}.train.trainer")


def read(out):
    """A step's loss terms: read from the device, or (older trainers) returned read."""
    return out.read()[0] if hasattr(out, "read") else out[0]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="training infos (odg prepare)")
    parser.add_argument("--against", default="main", help="git revision of the old package")
    parser.add_argument("--preset", default="odg_cpu")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-augment", action="store_true")
    args = parser.parse_args()
    cfg = load_preset(args.preset)

    with tempfile.TemporaryDirectory() as tmp:
        before = package_at(args.against, Path(tmp))

        def build(module, out):
            torch.manual_seed(0)
            wanted = dict(out_dir=out, workers=0, device="cpu", progress=False,
                          augment=not args.no_augment)
            known = {f.name for f in dataclasses.fields(module.TrainOptions)}
            return module.Trainer(cfg, args.data,
                                  module.TrainOptions(**{k: v for k, v in wanted.items()
                                                         if k in known}))

        trainers = {"before": build(before, Path(tmp) / "before"),
                    "this code": build(current, Path(tmp) / "now")}
        batches = list(itertools.islice(itertools.cycle(trainers["this code"].loader),
                                        args.repeats + 1))
        # revisions before the uint8 loader took images normalised by the loader's workers
        host_normalised = not hasattr(importlib.import_module(f"{OLD_NAME}.data.batch"),
                                      "to_device")
        inputs = {"before": (lambda b: dict(b, images=normalize(b["images"])))
                  if host_normalised else (lambda b: b),
                  "this code": lambda b: b}
        seconds = {name: [] for name in trainers}
        largest_difference = 0.0
        for index, batch in enumerate(batches):
            order = list(trainers) if index % 2 == 0 else list(trainers)[::-1]
            terms = {}
            for name in order:
                torch.manual_seed(1000 + index)
                start = time.perf_counter()
                terms[name] = read(trainers[name].train_step(inputs[name](batch)))
                elapsed = time.perf_counter() - start
                if index:                                     # the first is a warm-up
                    seconds[name].append(elapsed)
                print(f"step {index} {name}: {elapsed:.2f} s, "
                      f"loss {terms[name].get('loss', float('nan')):.6f}", flush=True)
            for key, value in terms["before"].items():
                new = terms["this code"][key]
                largest_difference = max(largest_difference,
                                         abs(new - value) / max(abs(value), 1e-12))
    medians = {name: statistics.median(v) for name, v in seconds.items()}
    for name, median in medians.items():
        print(f"{name:10s} median {median:.3f} s of {len(seconds[name])} steps")
    print(f"this code / before: {medians['this code'] / medians['before']:.3f} "
          f"(torch {torch.__version__}, {torch.get_num_threads()} threads)")
    print(f"largest relative difference of a loss term: {largest_difference:.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
