"""Accuracy of the query budgets per scene class, on the same keyframes
(odg_ros/bench/budget_accuracy.py): the full model, each rung of the ladder, ``auto``, and
with ``--baselines`` / ``--oracles`` / ``--margins`` the rankings and bounds to compare with.

    OMP_NUM_THREADS=1 python -m tools.eval_budget --checkpoint runs/budget/budget_heads.pt \
        --data quiet=data/quiet/infos_val.pkl dense=data/dense/infos_val.pkl --out eval.json
"""
from __future__ import annotations

import argparse
import sys

import torch

from odg_ros.bench.budget_accuracy import configurations, evaluate_class, scene_classes
from odg_ros.commands.common import positive_float
from odg_ros.data.dataset import load_infos_file
from odg_ros.network.checkpoint import load_model
from tools.gpu_tool import write_json


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--data", nargs="+", required=True)
    parser.add_argument("--limit", type=int, default=None)
    parser.add_argument("--baselines", action="store_true",
                        help="also random / best-point-score rankings, smaller sets")
    parser.add_argument("--oracles", action="store_true",
                        help="also the budgets ranked by a perfect keep-score (its target on "
                             "the keyframe) and by the ground-truth gain: bounds")
    parser.add_argument("--margins", type=positive_float, nargs="+", default=(),
                        help="also auto with these margins (online/budget_policy.py)")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    model, cfg = load_model(args.checkpoint)
    classes = {}
    for item in args.data:
        if "=" in item:
            name, path = item.split("=", 1)
            classes[name] = load_infos_file(path)
        else:
            classes.update(scene_classes(item))
    include = {name for name, wanted in (("baselines", args.baselines),
                                         ("oracles", args.oracles)) if wanted}
    configs = configurations(model, cfg, include, args.margins)
    results = {"checkpoint": args.checkpoint, "threads": torch.get_num_threads(),
               "classes": {}}
    for name, infos in classes.items():
        results["classes"][name] = evaluate_class(name, infos, model, cfg, configs, args.limit)
        write_json(args.out, results)           # each class as soon as it is scored
        for config, row in results["classes"][name].items():
            print(f"{name:8s} {config:22s} mIoU {row['mIoU']:6.2f} RayIoU {row['RayIoU']:6.2f} "
                  f"refined {row['refined_fraction']:.3f} decoder {row['decoder_ms']:.1f} ms",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
