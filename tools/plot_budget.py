"""Speed against error of the query budgets per scene class, as a picture
(odg_ros/bench/budget_plot.py), from the JSONs of ``tools.eval_budget`` and
``tools.profile_budget``.

    python -m tools.plot_budget --eval eval.json [eval2.json ...] --profile profile.json \
        --out docs/results/query_budget.png
"""
from __future__ import annotations

import argparse
import json
import sys

from odg_ros.bench.budget_plot import plot_budget_study


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--eval", nargs="+", required=True, help="tools.eval_budget JSONs")
    parser.add_argument("--profile", required=True, help="tools.profile_budget JSON")
    parser.add_argument("--out", required=True, help="PNG to write")
    args = parser.parse_args(argv)
    classes = {}
    for path in args.eval:
        with open(path) as f:
            classes.update(json.load(f)["classes"])
    with open(args.profile) as f:
        profile = json.load(f)[0]
    plot_budget_study(classes, profile, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
