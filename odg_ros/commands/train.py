"""``odg train --preset NAME --data INFOS --out DIR [...]`` (also under torchrun for DDP), and
``odg train --budget-heads --init CHECKPOINT --data INFOS --out DIR``: the query-budget heads
of a trained checkpoint, every other weight frozen."""
from __future__ import annotations

import argparse
import json
import logging
import sys
import traceback
from pathlib import Path

from ..model_config import load_preset
from ..train.budget_heads import BudgetHeadTraining, train_budget_heads
from ..train.trainer import Trainer, TrainOptions, end_distributed
from .common import (add_backbone_start_options, add_device_option, add_preset_option,
                     add_render_pixels_option, add_set_option, config_overrides, existing_file,
                     infos_file, nonnegative_int, positive_float, positive_int)

parse_overrides = config_overrides      # eval and the tools import it from here


def add_arguments(parser):
    add_preset_option(parser)
    parser.add_argument("--data", required=True, nargs="+", type=infos_file,
                        help="training infos (odg prepare); several files train together")
    parser.add_argument("--out", required=True, help="output dir: checkpoints, train_log.csv")
    parser.add_argument("--epochs", type=positive_int, default=24,
                        help="passes over the data (the paper trains 100; hours on GPUs)")
    parser.add_argument("--steps", type=positive_int, default=None,
                        help="stop after this many optimiser steps (default: run all epochs)")
    parser.add_argument("--batch-size", type=positive_int, default=1, help="samples per process")
    parser.add_argument("--lr", type=positive_float, default=2e-4, help="peak learning rate")
    parser.add_argument("--warmup", type=nonnegative_int, default=200, help="warm-up steps")
    parser.add_argument("--backbone-lr-mult", type=positive_float, default=0.1,
                        help="backbone lr factor (0.1 for an ImageNet-pretrained backbone; "
                             "1.0 when it trains from scratch)")
    parser.add_argument("--workers", type=nonnegative_int, default=2,
                        help="data-loading processes per training process (0: in-process)")
    add_device_option(parser)
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    parser.add_argument("--no-render", action="store_true",
                        help="ablation: no Gaussian-splatting rendering supervision")
    add_render_pixels_option(parser)
    parser.add_argument("--renderer", choices=("auto", "torch", "gsplat"), default="auto",
                        help="render loss (auto: gsplat on CUDA when installed, else ours): our "
                             "PyTorch renderer (any device), or gsplat's CUDA "
                             "rasteriser (whole images, alpha capped at 0.999 not 0.99)")
    parser.add_argument("--no-history-grad", action="store_true",
                        help="backbone gradients through the current frame only (faster, "
                             "SparseBEV's stop_prev_grad)")
    parser.add_argument("--no-augment", action="store_true",
                        help="no data augmentation (flip, resize-and-crop, photometric)")
    parser.add_argument("--checkpoint-backbone", action="store_true",
                        help="gradient checkpointing of the backbone: its stages run again in "
                             "the backward pass instead of keeping their activations (less "
                             "memory, about one more backbone forward; default: off; needs "
                             "frozen BatchNorm, as with --backbone-weights)")
    parser.add_argument("--compile", action="store_true",
                        help="torch.compile the model's forward (the first step compiles, "
                             "minutes for ODG-T; default: off, eager)")
    add_set_option(parser, help="model config override, repeatable, e.g. --set das_attention=false "
                             "(the keys of model/odg_cpu.yaml; default: the preset as it is)")
    add_backbone_start_options(parser)
    parser.add_argument("--init", type=existing_file,
                        help="start from this checkpoint's weights (default: fresh weights)")
    parser.add_argument("--checkpoint-every", type=positive_int, default=500,
                        help="steps between OUT/latest.pt saves")
    parser.add_argument("--log-every", type=positive_int, default=10,
                        help="steps between reads of the losses from the device (default: 10; "
                             "each read waits for the GPU, so rarely is faster; every step "
                             "still gets its log row, and checkpoints read first)")
    parser.add_argument("--resume", action="store_true", help="continue OUT/latest.pt")
    _add_budget_head_arguments(parser)


def _add_budget_head_arguments(parser):
    heads = parser.add_argument_group(
        "budget heads", "--budget-heads trains the query-budget heads of the --init checkpoint "
        "(docs/query_budget.md), every other weight frozen, and writes OUT/budget_heads.pt "
        "(model and heads), OUT/budget_heads.pt.log and the cached model pass in OUT/cache/ "
        "(a stopped pass resumes); the options above other than --data, --out and --init do "
        "not apply")
    defaults = BudgetHeadTraining()
    heads.add_argument("--budget-heads", action="store_true",
                       help="train the budget heads instead of the model")
    heads.add_argument("--keyframes", type=positive_int, default=None,
                       help="keyframes per infos file (default: all)")
    heads.add_argument("--skip-epochs", type=positive_int, default=defaults.skip_epochs,
                       help="passes distilling the skip layer")
    heads.add_argument("--skip-lr", type=positive_float, default=defaults.skip_lr,
                       help="the skip layer's learning rate")
    heads.add_argument("--keep-epochs", type=positive_int, default=defaults.keep_epochs,
                       help="passes fitting the keep-scores")
    heads.add_argument("--calibration-keyframes", type=positive_int,
                       default=defaults.calibration_keyframes,
                       help="cached keyframes (evenly spaced) the skip layer's logit offset is "
                            "chosen on")
    heads.add_argument("--need-change", type=positive_float, default=defaults.need_change,
                       help="a query whose refinement is predicted to change its part of the "
                            "grid by more than this counts as needed by query_budget auto")


HEAD_OPTIONS = ("keyframes", "skip_epochs", "skip_lr", "keep_epochs", "calibration_keyframes",
                "need_change")
COMMON_OPTIONS = ("data", "out", "init", "budget_heads")


def _explicit_options(args) -> set[str]:
    """The options of ``args`` given other values than their defaults."""
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return {name for name, value in vars(args).items()
            if name in {action.dest for action in parser._actions}
            and name not in ("data", "out") and value != parser.get_default(name)}


def _flags(names) -> str:
    return ", ".join("--" + name.replace("_", "-") for name in sorted(names))


def _train_budget_heads(args) -> int:
    misplaced = _explicit_options(args) - set(HEAD_OPTIONS) - set(COMMON_OPTIONS)
    if misplaced:
        raise ValueError(f"with --budget-heads, {_flags(misplaced)} do not apply (they train "
                         "the model)")
    if args.init is None:
        raise ValueError("--budget-heads needs --init CHECKPOINT (the trained model "
                         "whose heads to train)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    options = BudgetHeadTraining(
        skip_epochs=args.skip_epochs, skip_lr=args.skip_lr, keep_epochs=args.keep_epochs,
        calibration_keyframes=args.calibration_keyframes, need_change=args.need_change,
        keyframes_per_file=args.keyframes)
    report = train_budget_heads(args.init, args.data, out / "budget_heads.pt", out / "cache",
                                options)
    print(json.dumps(report, indent=2))
    print(f"wrote {out / 'budget_heads.pt'} (log: {out / 'budget_heads.pt.log'})")
    return 0


def run(args) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if args.budget_heads:
        return _train_budget_heads(args)
    misplaced = _explicit_options(args) & set(HEAD_OPTIONS)
    if misplaced:
        raise ValueError(f"{_flags(misplaced)} train the budget heads: they need "
                         "--budget-heads")
    cfg = load_preset(args.preset, **config_overrides(args.set))
    opts = TrainOptions(out_dir=args.out, epochs=args.epochs, max_steps=args.steps,
                        batch_size=args.batch_size, lr=args.lr, warmup_steps=args.warmup,
                        backbone_lr_mult=args.backbone_lr_mult,
                        workers=args.workers, seed=args.seed, render=not args.no_render,
                        render_pixels_per_camera=args.render_pixels, renderer=args.renderer,
                        history_grad=not args.no_history_grad, augment=not args.no_augment,
                        checkpoint_backbone=args.checkpoint_backbone, compile=args.compile,
                        checkpoint_every=args.checkpoint_every, log_every=args.log_every,
                        device=args.device,
                        backbone_weights=args.backbone_weights,
                        backbone_from_scratch=args.backbone_from_scratch,
                        init_checkpoint=args.init,
                        resume=args.resume)
    try:
        summary, rank = _fit(cfg, args.data, opts)
    except BaseException as error:
        traceback.clear_frames(error.__traceback__)  # they hold the Trainer: let it go first
        raise
    finally:
        end_distributed()
    if rank == 0:
        out = Path(args.out)
        summary["wrote"] = {"weights": str(out / "final.pt"), "resume": str(out / "latest.pt"),
                            "log": str(out / "train_log.csv")}
        print(json.dumps(summary, indent=2))
        print(f"odg train: wrote {out / 'final.pt'} (the trained model: odg eval / odg export "
              f"--checkpoint), {out / 'latest.pt'} (odg train --resume) and "
              f"{out / 'train_log.csv'}", file=sys.stderr)
    return 0


def _fit(cfg, data, opts) -> tuple[dict, int]:
    """The Trainer (and the DDP wrapper holding the process group) lives only in here, so
    that end_distributed can free it."""
    trainer = Trainer(cfg, data, opts)
    return trainer.fit(), trainer.rank
