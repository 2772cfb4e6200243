"""``odg train --preset NAME --data INFOS --out DIR [...]`` (also under torchrun for DDP)."""
from __future__ import annotations

import json
import logging
import traceback

import yaml

from ..config import load_preset
from ..train.trainer import Trainer, TrainOptions, end_distributed


def parse_overrides(items: list[str]) -> dict:
    """``["key=value", ...]`` -> dict with YAML-typed values (e.g. das_attention=false)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise SystemExit(f"--set expects key=value, got {item!r}")
        key, value = item.split("=", 1)
        out[key.strip()] = yaml.safe_load(value)
    return out


def add_arguments(parser):
    parser.add_argument("--preset", default="odg_cpu")
    parser.add_argument("--data", required=True, nargs="+",
                        help="training infos (odg prepare); several files train together")
    parser.add_argument("--out", required=True, help="output dir: checkpoints, train_log.csv")
    parser.add_argument("--epochs", type=int, default=24)
    parser.add_argument("--steps", type=int, default=None, help="stop after this many steps")
    parser.add_argument("--batch-size", type=int, default=1, help="per process")
    parser.add_argument("--lr", type=float, default=2e-4)
    parser.add_argument("--warmup", type=int, default=200, help="warm-up steps")
    parser.add_argument("--backbone-lr-mult", type=float, default=0.1,
                        help="backbone lr factor (0.1 for an ImageNet-pretrained backbone; "
                             "1.0 when it trains from scratch)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-render", action="store_true",
                        help="ablation: no Gaussian-splatting rendering supervision")
    parser.add_argument("--render-pixels", type=int, default=512,
                        help="supervised LiDAR pixels per camera and step")
    parser.add_argument("--renderer", choices=("torch", "gsplat"), default="torch",
                        help="render loss: our PyTorch renderer (any device), or gsplat's CUDA "
                             "rasteriser (whole images, alpha capped at 0.999 not 0.99)")
    parser.add_argument("--no-history-grad", action="store_true",
                        help="backbone gradients through the current frame only (faster, "
                             "SparseBEV's stop_prev_grad)")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="model config override, e.g. --set das_attention=false")
    parser.add_argument("--backbone-weights", help="torchvision-layout ResNet .pth to start from")
    parser.add_argument("--init", help="start from this checkpoint's weights")
    parser.add_argument("--checkpoint-every", type=int, default=500)
    parser.add_argument("--resume", action="store_true", help="continue OUT/latest.pt")


def run(args) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    cfg = load_preset(args.preset, **parse_overrides(args.set))
    opts = TrainOptions(out_dir=args.out, epochs=args.epochs, max_steps=args.steps,
                        batch_size=args.batch_size, lr=args.lr, warmup_steps=args.warmup,
                        backbone_lr_mult=args.backbone_lr_mult,
                        workers=args.workers, seed=args.seed, render=not args.no_render,
                        render_pixels_per_camera=args.render_pixels, renderer=args.renderer,
                        history_grad=not args.no_history_grad,
                        checkpoint_every=args.checkpoint_every, device=args.device,
                        backbone_weights=args.backbone_weights, init_checkpoint=args.init,
                        resume=args.resume)
    try:
        summary, rank = _fit(cfg, args.data, opts)
    except BaseException as error:
        traceback.clear_frames(error.__traceback__)  # they hold the Trainer: let it go first
        raise
    finally:
        end_distributed()
    if rank == 0:
        print(json.dumps(summary, indent=2))
    return 0


def _fit(cfg, data, opts) -> tuple[dict, int]:
    """The Trainer (and the DDP wrapper holding the process group) lives only in here, so
    that end_distributed can free it."""
    trainer = Trainer(cfg, data, opts)
    return trainer.fit(), trainer.rank
