"""Checkpoints: ``{"config": ModelConfig dict, "model": state_dict, ...}``, written atomically."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import torch

from ..config import ModelConfig, load_preset
from .odg import ODG


INT8_PREFIX = "__int8__"


def quantize_int8(t: torch.Tensor) -> dict:
    """Symmetric per-output-channel int8 of a weight tensor (dim >= 2)."""
    flat = t.detach().float().reshape(t.shape[0], -1)
    scale = (flat.abs().amax(dim=1) / 127.0).clamp(min=1e-12)
    q = torch.round(flat / scale[:, None]).clamp(-127, 127).to(torch.int8)
    return {"q": q.reshape(t.shape), "scale": scale}


def dequantize_int8(packed: dict) -> torch.Tensor:
    q = packed["q"]
    return (q.float().reshape(q.shape[0], -1) * packed["scale"][:, None]).reshape(q.shape)


def compress_state(state: dict, mode: str | None) -> dict:
    """mode None: as is; "fp16": floating tensors in half; "int8": weights (dim >= 2) in int8
    with per-output-channel scales, the other floating tensors in half (shipping size)."""
    if mode is None:
        return dict(state)
    if mode not in ("fp16", "int8"):
        raise ValueError(f"unknown checkpoint compression {mode!r}")
    out = {}
    for k, v in state.items():
        if mode == "int8" and v.is_floating_point() and v.dim() >= 2:
            out[INT8_PREFIX + k] = quantize_int8(v)
        else:
            out[k] = v.half() if v.is_floating_point() else v
    return out


def decompress_state(state: dict) -> dict:
    return {(k[len(INT8_PREFIX):] if k.startswith(INT8_PREFIX) else k):
            (dequantize_int8(v) if k.startswith(INT8_PREFIX) else v) for k, v in state.items()}


def save_checkpoint(path, model: ODG, extra: dict | None = None,
                    compress: str | None = None) -> None:
    """Atomic write (temp file + rename) so a crash never leaves a truncated checkpoint.
    ``compress`` ("fp16" | "int8", see compress_state) shrinks a shipped checkpoint; loading
    casts everything back to the model's float32."""
    state = compress_state(model.state_dict(), compress)
    payload = {"config": model.cfg.to_dict(), "model": state, "compression": compress,
               **(extra or {})}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    os.close(fd)
    try:
        torch.save(payload, tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def load_model(path=None, preset: str = "odg_cpu", device="cpu", **overrides):
    """-> (model in eval mode on ``device``, config). ``path`` None: random weights of ``preset``."""
    if path is None:
        cfg = load_preset(preset, **overrides)
        model = ODG(cfg)
    else:
        payload = torch.load(path, map_location="cpu", weights_only=False)
        cfg = ModelConfig(**{**payload["config"], **overrides})
        model = ODG(cfg)
        own = model.state_dict()
        state = {k: v.to(own[k].dtype) if k in own else v
                 for k, v in decompress_state(payload["model"]).items()}
        model.load_state_dict(state)
    return model.to(device).eval(), cfg
