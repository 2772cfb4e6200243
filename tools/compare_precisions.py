"""Scores of ``odg eval --precision P --json --save-pred DIR/pred-P`` runs side by side, per
scene class, with the share of voxels whose label equals a reference precision's.

    for P in fp32 bf16-encoder int8-encoder; do
      odg eval --checkpoint model/odg_cpu.pt --precision $P --json --save-pred OUT/pred-$P \\
          --data city-quiet=data/held_out/city-quiet/infos_all.pkl ... > OUT/$P.json
    done
    python -m tools.compare_precisions --dir OUT --data city-quiet=data/held_out/... \\
        [--precisions fp32 bf16-encoder int8-encoder] [--reference bf16-encoder]

Prints a Markdown table: mIoU, RayIoU, box mAP, AP@2, mATE, and the label agreement with the
reference over all voxels and over those either calls occupied.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from odg_ros.data.prepare import load_infos


def agreement(folder: Path, reference: Path, tokens: list[str], free: int):
    same = total = occupied = occupied_same = 0
    for token in tokens:
        a = np.load(folder / f"{token}.npz")["semantics"]
        b = np.load(reference / f"{token}.npz")["semantics"]
        either = (a != free) | (b != free)
        same += int((a == b).sum())
        total += a.size
        occupied += int(either.sum())
        occupied_same += int(((a == b) & either).sum())
    return same / total, occupied_same / max(occupied, 1)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dir", required=True, type=Path)
    parser.add_argument("--data", required=True, nargs="+", metavar="NAME=INFOS")
    parser.add_argument("--precisions", nargs="+",
                        default=["fp32", "bf16-encoder", "int8-encoder"])
    parser.add_argument("--reference", default="bf16-encoder")
    parser.add_argument("--free-label", type=int, default=17, help="Occ3D's free (17)")
    args = parser.parse_args(argv)
    sets = dict(item.split("=", 1) for item in args.data)
    tokens = {name: [i["token"] for i in load_infos(path)["infos"]]
              for name, path in sets.items()}
    tokens["all"] = [t for name in sets for t in tokens[name]]
    results = {p: json.loads((args.dir / f"{p}.json").read_text()) for p in args.precisions}
    print(f"| set | precision | mIoU | RayIoU | box mAP | AP@2 | mATE | labels = "
          f"{args.reference} (all / occupied) |")
    print("|---|---|---|---|---|---|---|---|")
    for name in [*sets, "all"]:
        for p in args.precisions:
            r = results[p] if name == "all" else results[p]["sets"][name]
            b = r["boxes"]
            voxels, occupied = agreement(args.dir / f"pred-{p}",
                                         args.dir / f"pred-{args.reference}", tokens[name],
                                         args.free_label)
            print(f"| {name} | {p} | {r['mIoU']:.2f} | {r['RayIoU']:.2f} | {b['mAP']:.2f} | "
                  f"{b['AP@2']:.2f} | {b['mATE']:.3f} | {voxels:.4f} / {occupied:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
