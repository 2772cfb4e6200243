"""CPU time of one training step, this code's trainer against an earlier revision of
odg_ros/train/trainer.py, in one process, interleaved, medians.

    python tools/bench_train_step.py --data INFOS [--against main] [--preset odg_cpu]
        [--repeats 5]

Both trainers are built alike (same seed, so the same initial weights) and take the same
batches in turn, one warm-up step each first. A step is timed with the read of its losses
(this code reads them in ``fit`` every ``--log-every`` steps; here after every step).
"""
import argparse
import itertools
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from revision import module_at  # noqa: E402
from odg_ros.config import load_preset  # noqa: E402
from odg_ros.preprocess import normalize  # noqa: E402
from odg_ros.train import trainer as current  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="training infos (odg prepare)")
    parser.add_argument("--against", default="main", help="git revision of the old trainer")
    parser.add_argument("--preset", default="odg_cpu")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    cfg = load_preset(args.preset)
    before = module_at(args.against, "odg_ros/train/trainer.py")

    def build(module, out):
        opts = module.TrainOptions(out_dir=out, workers=0, device="cpu", progress=False)
        return module.Trainer(cfg, args.data, opts)

    with tempfile.TemporaryDirectory() as tmp:
        trainers = {"before": build(before, Path(tmp) / "before"),
                    "this code": build(current, Path(tmp) / "now")}
        batches = list(itertools.islice(itertools.cycle(trainers["this code"].loader),
                                        args.repeats + 1))
        # normalised on the host, as trainers before the uint8 loader expect; this code's
        # upload leaves float images as they are
        batches = [dict(b, images=normalize(b["images"])) for b in batches]
        def read(out):   # a step's values on the device, or (older trainers) read already
            return out.read()[0] if hasattr(out, "read") else out[0]
        seconds = {name: [] for name in trainers}
        for index, batch in enumerate(batches):
            order = list(trainers) if index % 2 == 0 else list(trainers)[::-1]
            for name in order:
                start = time.perf_counter()
                terms = read(trainers[name].train_step(batch))
                if index:                                     # the first is a warm-up
                    seconds[name].append(time.perf_counter() - start)
                print(f"step {index} {name}: {time.perf_counter() - start:.2f} s, "
                      f"loss {terms.get('loss', float('nan')):.4f}", flush=True)
    medians = {name: statistics.median(v) for name, v in seconds.items()}
    for name, median in medians.items():
        print(f"{name:10s} median {median:.3f} s of {len(seconds[name])} steps")
    print(f"this code / before: {medians['this code'] / medians['before']:.3f} "
          f"(torch {torch.__version__}, {torch.get_num_threads()} threads)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
