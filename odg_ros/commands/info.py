"""``odg info [--preset NAME] [--json]``: size and cost of a preset (default odg_cpu, as
every command that takes one)."""
from __future__ import annotations

import json

from torch.utils.flop_counter import FlopCounterMode

from ..nuscenes_cameras import online_inputs
from ..model_config import load_preset
from ..network import ODG
from .common import add_json_option, add_preset_option


def add_arguments(parser):
    add_preset_option(parser)
    add_json_option(parser)


def preset_info(cfg) -> dict:
    model = ODG(cfg).eval()
    parts = model.parameter_groups()
    images, ego2img, ego_warp, time_delta = online_inputs(cfg, cfg.num_frames, "cpu")
    # FLOPs of one online step: backbone on the newest frame, decoder over all frames.
    # Autograd stays on: torch's FLOP counter's module tracker fails under no_grad.
    with FlopCounterMode(display=False) as backbone_flops:
        feats = model.extract_features(images)
    with FlopCounterMode(display=False) as decoder_flops:
        model.decode([feats] * cfg.num_frames, ego2img, ego_warp, time_delta)
    gb, gd = backbone_flops.get_total_flops() / 1e9, decoder_flops.get_total_flops() / 1e9
    return {
        "preset": cfg.name,
        "params_total": sum(p.numel() for p in model.parameters()),
        "params": parts,
        "queries": {"dynamic": cfg.dynamic_queries, "static": cfg.static_queries},
        "gaussians_per_layer": cfg.gaussians_per_layer,
        "input": [cfg.num_cams, 3, *cfg.image_size],
        "frames": cfg.num_frames,
        "gflops_per_frame": round(gb + gd, 2),
        "gflops": {"backbone": round(gb, 2), "decoder": round(gd, 2)},
    }


def run(args) -> int:
    info = preset_info(load_preset(args.preset))
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(f"preset {info['preset']}: {info['params_total'] / 1e6:.2f} M parameters")
    for part, n in info["params"].items():
        print(f"  {part:<9} {n / 1e6:8.2f} M")
    print(f"queries: {info['queries']['dynamic']} dynamic + {info['queries']['static']} static")
    print(f"Gaussians per layer: {info['gaussians_per_layer']}")
    print(f"input: {info['input']} x {info['frames']} frames")
    print(f"GFLOPs per online step: {info['gflops_per_frame']} "
          f"(backbone {info['gflops']['backbone']}, decoder {info['gflops']['decoder']})")
    return 0
