"""Train the query-budget heads (skip layer, keep-scores, then the skip layer's calibrated
logit offset) of a trained checkpoint, every other weight frozen
(odg_ros/train/budget_heads.py), and write the checkpoint with them.

    OMP_NUM_THREADS=1 python -m tools.train_budget_heads --checkpoint model/odg_cpu.pt \
        --data data/synth24/infos_train.pkl --cache runs/budget/cache --out runs/budget/odg_cpu.pt

The model's pass over the keyframes is the slow part (about 1.5 s each on one core); it is
cached in ``--cache`` (one file per keyframe, ~25 MB for odg_cpu; a stopped pass resumes), so
that the heads can be refitted in minutes. Progress goes to OUT.log.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from odg_ros.commands.common import positive_int
from odg_ros.data.dataset import OccDataset
from odg_ros.network.budget import budget_ladder
from odg_ros.network.checkpoint import load_model, read_checkpoint, save_checkpoint
from odg_ros.train import budget_heads as heads


def arguments(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True, help="the trained model")
    parser.add_argument("--data", required=True, nargs="+", help="training infos (odg prepare)")
    parser.add_argument("--cache", required=True, help="folder of the cached model pass")
    parser.add_argument("--out", required=True, help="checkpoint to write (model + heads)")
    parser.add_argument("--limit", type=int, default=None, help="keyframes per infos file")
    parser.add_argument("--skip-epochs", type=int, default=20)
    parser.add_argument("--skip-lr", type=float, default=1e-3)
    parser.add_argument("--keep-epochs", type=int, default=40)
    parser.add_argument("--calibration-keyframes", type=positive_int, default=96,
                        help="cached keyframes (evenly spaced) the skip layer's logit offset "
                             "is chosen on")
    parser.add_argument("--need-change", type=float, default=heads.NEED_CHANGE,
                        help="a query whose refinement is predicted to change its part of the "
                             "grid by more than this (train/budget_heads.refinement_change) "
                             "counts as needed by query_budget auto")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = arguments(argv)
    log_file = open(args.out + ".log", "a")

    def log(text):
        print(f"{time.strftime('%H:%M:%S')} {text}", file=log_file, flush=True)
    model, cfg = load_model(args.checkpoint)
    payload = read_checkpoint(args.checkpoint)
    files = []
    for infos in args.data:
        dataset = OccDataset(infos, cfg, train=False)
        indices = list(range(len(dataset)))[:args.limit]
        start = time.time()
        name = Path(infos).parent.name + "-" + Path(infos).stem
        files += heads.collect(model, dataset, indices, args.cache, desc=name)
        log(f"model pass over {len(indices)} keyframes of {infos}: {time.time() - start:.0f} s")
    heads.init_skip_layer(model)
    skip = heads.fit_skip_layer(model, files, epochs=args.skip_epochs, lr=args.skip_lr, log=log)
    changes, states = heads.refinement_change(model, files)
    keep = heads.fit_keep_scores(model, states, changes, epochs=args.keep_epochs, log=log)
    step = max(1, len(files) // args.calibration_keyframes)
    calibration = heads.calibrate_skip_layer(model, files[::step], budget_ladder(cfg)[1:],
                                             log=log)
    model.decoder.budget_heads.set_trained(
        True, float(heads.squashed(torch.tensor(args.need_change))))
    report = {"source": args.checkpoint, "data": args.data, "keyframes": len(files),
              "need_change": args.need_change, "skip_epochs": args.skip_epochs,
              "skip_lr": args.skip_lr, "keep_epochs": args.keep_epochs,
              "skip_layer_loss": skip, "keep_score_loss": keep,
              "skip_logit_offset": calibration["offset"],
              "skip_offset_agreement": calibration["agreement"]}
    save_checkpoint(args.out, model, extra={"budget_heads": report,
                                            **({"export": payload["export"]}
                                               if "export" in payload else {})},
                    compress=payload.get("compression"))
    log(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
