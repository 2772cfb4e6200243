"""Where the node's step spends its time at each query budget, and what a smaller budget
saves: milliseconds, ATen ops and FLOPs per part of the decoder
(odg_ros/bench/budget_cost.py).

    OMP_NUM_THREADS=1 python -m tools.profile_budget --presets odg_cpu odg_t odg_l \
        --iters 3 --out profile.json
"""
from __future__ import annotations

import argparse
import json
import sys

import torch

from odg_ros.bench.budget_cost import profile_preset, summary
from odg_ros.model_config import load_preset
from odg_ros.network import ODG
from odg_ros.network.checkpoint import load_model


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["odg_cpu", "odg_t", "odg_l"])
    parser.add_argument("--checkpoint", default=None)
    parser.add_argument("--iters", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    results = []
    for index, preset in enumerate(args.presets):
        torch.manual_seed(0)
        if index == 0 and args.checkpoint:
            model, cfg = load_model(args.checkpoint)
        else:
            cfg = load_preset(preset)
            model = ODG(cfg).eval()
        results.append(profile_preset(cfg, model, args.iters, args.warmup))
        print(json.dumps(summary(results[-1])), flush=True)
        if args.out:
            with open(args.out, "w") as f:
                json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
