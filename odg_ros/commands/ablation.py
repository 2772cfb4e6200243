"""``odg ablation NAME=EVAL_JSON ... --out STEM``: the paper's Table 4 on our data.

Reads ``odg eval --json`` results (a name may repeat: one file per training seed; the first
name is the reference) and writes ``STEM.json``, ``STEM.md`` and ``STEM.png``
(``odg_ros/bench/ablation.py``)."""
from __future__ import annotations

import json
from pathlib import Path

from .common import UserError


def add_arguments(parser):
    parser.add_argument("runs", nargs="+", metavar="NAME=EVAL_JSON",
                        help="the first name is the reference; repeat a name for its seeds")
    parser.add_argument("--out", required=True, help="output stem: writes .json, .md, .png")


def run(args) -> int:
    from ..bench.ablation import ablation_table, summarize_ablation, write_ablation
    runs = []
    for item in args.runs:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise UserError(f"expected NAME=EVAL_JSON, got {item!r}")
        try:
            runs.append((name, json.loads(Path(path).read_text())))
        except json.JSONDecodeError as error:
            raise UserError(f"{path}: not an odg eval --json result ({error})") from None
    summary = summarize_ablation(runs)
    write_ablation(summary, Path(args.out))
    print(ablation_table(summary), end="")
    return 0
