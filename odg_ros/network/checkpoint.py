"""Checkpoints: ``{"config": ModelConfig dict, "model": state_dict, ...}``, written atomically."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import torch

from ..config import ModelConfig, load_preset
from .odg import ODG


def save_checkpoint(path, model: ODG, extra: dict | None = None, half: bool = False) -> None:
    """Atomic write (temp file + rename) so a crash never leaves a truncated checkpoint.
    ``half`` stores floating tensors as fp16 (shipping size); loading casts them back."""
    state = {k: (v.half() if half and v.is_floating_point() else v)
             for k, v in model.state_dict().items()}
    payload = {"config": model.cfg.to_dict(), "model": state, **(extra or {})}
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
        state = {k: v.to(own[k].dtype) if k in own else v for k, v in payload["model"].items()}
        model.load_state_dict(state)
    return model.to(device).eval(), cfg
