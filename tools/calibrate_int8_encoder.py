"""Write the int8 encoder's activation ranges (``model/int8/<fingerprint>.json``) for a
checkpoint: its float encoder, as the node's step runs it, over the keyframe camera images of
TRAINING worlds (never the held-out ones it is scored on), histogram observers per activation.

    python -m tools.calibrate_int8_encoder --checkpoint model/odg_cpu.pt \
        --data data/calib/*/infos_all.pkl [--per-world 12] [--out-dir model/int8]

The file is a few KB and deterministic for the same images; ``precision: int8-encoder`` then
loads it at start (network/int8_encoder.py) instead of calibrating there.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from odg_ros.data.dataset import OccDataset
from odg_ros.network import int8_encoder
from odg_ros.network.checkpoint import load_model
from odg_ros.online.step import OnlineStep


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--data", required=True, nargs="+", help="training infos_all.pkl files")
    parser.add_argument("--per-world", type=int, default=12,
                        help="keyframes per infos file, evenly spaced (default 12)")
    parser.add_argument("--out-dir", default=int8_encoder.RANGES_DIR)
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    model, cfg = load_model(args.checkpoint)
    step = OnlineStep(model, cfg, cfg.num_frames, "cpu", "fp32", visibility=False)
    batches = []
    for infos in args.data:
        dataset = OccDataset(infos, cfg, train=False)
        picks = np.unique(np.linspace(0, len(dataset) - 1, args.per_world).round().astype(int))
        for index in tqdm(picks, desc=f"images {Path(infos).parent.name}"):
            images = dataset[int(index)]["images"][0]                 # keyframe [N, H, W, 3]
            x = ((images.float() / 255.0 - step.mean) / step.std).movedim(-1, -3)
            batches.append(x)
    fingerprint = int8_encoder.encoder_fingerprint(model.backbone, model.neck)
    content = int8_encoder.calibrate(step.backbone, step.neck, batches, fingerprint,
                                     progress=lambda items: tqdm(items, desc="calibrate"))
    content["checkpoint"] = Path(args.checkpoint).name
    content["data"] = [Path(p).parent.name for p in args.data]
    out = int8_encoder.ranges_path(fingerprint, root=args.out_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(content, indent=1) + "\n")
    print(f"{out}: {len(content['ranges'])} activation ranges from {content['images']} images")
    return 0


if __name__ == "__main__":
    sys.exit(main())
