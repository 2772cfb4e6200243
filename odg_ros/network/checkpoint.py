"""Checkpoints: ``{"config": ModelConfig dict, "model": state_dict, ...}``, written atomically."""
from __future__ import annotations

import errno
import math
import os
import shutil
import tempfile
from pathlib import Path

import torch

from ..model_config import ModelConfig, load_preset
from .odg import ODG


INT8_PREFIX = "__int8__"
BUDGET_HEADS = "decoder.budget_heads."       # network/budget.py: optional in a checkpoint


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
                    compress: str | None = None, state: dict | None = None) -> None:
    """Atomic write (temp file + rename) so a crash never leaves a truncated checkpoint.
    ``compress`` ("fp16" | "int8", see compress_state) shrinks a shipped checkpoint; loading
    casts everything back to the model's float32. ``state``: the weights as stored already
    compressed that way (written as they are), instead of the model's."""
    state = compress_state(model.state_dict(), compress) if state is None else state
    payload = {"config": model.cfg.to_dict(), "model": state, "compression": compress,
               **(extra or {})}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    os.close(fd)
    try:
        torch.save(payload, tmp)
        os.replace(tmp, path)
    except (OSError, RuntimeError) as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)  # before measuring the room: its partial bytes are not free
        # torch reports a full disk as e.g. "[enforce fail at inline_container.cc] unexpected
        # pos 576 vs 534", which names neither the file nor the cause
        free, needed = shutil.disk_usage(path.parent).free, tensor_bytes(payload)
        if free < needed:
            raise OSError(errno.ENOSPC, f"no room to write the checkpoint {path}: it needs "
                          f"about {needed / 1e6:.0f} MB, {free / 1e6:.0f} MB are free on its "
                          f"disk ({exc})") from exc
        raise
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def tensor_bytes(obj) -> int:
    """Bytes of the tensors in a nested checkpoint payload."""
    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, dict):
        return sum(tensor_bytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(tensor_bytes(v) for v in obj)
    return 0


def grow_state_dict(state: dict, model: ODG) -> dict:
    """``state`` (a trained checkpoint) for a ``model`` that is larger in two ways only, so
    that a trained model can grow instead of being retrained from scratch:
    * a decoder layer emits more points per query (K_new a multiple of K_old): each point of
      the head becomes K_new / K_old copies with the same class logits, the copies spread over
      a grid of neighbouring voxels (x, y) so they start in different voxels;
    * more dynamic queries: the trained dynamic and static queries are kept, the new dynamic
      ones start as ``model`` initialised them (zero features, uniform means and boxes).
    Any other shape difference is an error. The query-budget heads are never grown: a state
    without them (from before query budgets) or with heads of another shape gets the model's
    own untrained ones (``trained`` false: it runs the full query budget only)."""
    own = model.state_dict()
    num_dynamic = model.cfg.dynamic_queries
    old_dynamic = len(state.get("queries.init_box", own["queries.init_box"]))
    budget_heads = {k: v for k, v in own.items() if k.startswith(BUDGET_HEADS)}
    if all(k in state and state[k].shape == v.shape for k, v in budget_heads.items()):
        budget_heads = {k: state[k] for k in budget_heads}
    grown = {k: v for k, v in state.items() if not k.startswith(BUDGET_HEADS)}
    for key, tensor in list(grown.items()):
        if key.startswith("queries.") and key in own and old_dynamic != num_dynamic:
            grown[key] = _grow_queries(key, tensor, own[key], old_dynamic, num_dynamic)
        elif key in own and own[key].shape != tensor.shape:
            grown[key] = _grow_point_head(key, tensor, own[key], model.cfg)
    return {**grown, **budget_heads}


def _grow_queries(key, tensor, fresh, old_dynamic, num_dynamic):
    # rows are [dynamic; static] (init_box: dynamic only); the static count must not change
    if (tensor.shape[1:] != fresh.shape[1:] or old_dynamic > num_dynamic
            or len(tensor) - old_dynamic != len(fresh) - num_dynamic):
        raise ValueError(f"{key}: cannot grow {old_dynamic} dynamic queries "
                         f"{tuple(tensor.shape)} to {num_dynamic} {tuple(fresh.shape)}")
    grown = fresh.clone()
    grown[:old_dynamic] = tensor[:old_dynamic]                 # trained dynamic queries
    grown[num_dynamic:] = tensor[old_dynamic:]                 # trained static queries
    return grown


def _grow_point_head(key, tensor, fresh, cfg):
    head = key.rsplit(".", 3)    # decoder.layers.N.points | cls/reg | index | weight/bias
    if len(head) != 4 or not head[0].endswith(".points") or head[1] not in ("cls", "reg"):
        raise ValueError(f"{key}: checkpoint {tuple(tensor.shape)} vs model "
                         f"{tuple(fresh.shape)}, and it is not a point head or a query table")
    per_point = cfg.num_classes if head[1] == "cls" else 3
    old_k, new_k = tensor.shape[0] // per_point, fresh.shape[0] // per_point
    if new_k % old_k or tensor.shape[1:] != fresh.shape[1:]:
        raise ValueError(f"{key}: cannot grow {old_k} points per query to {new_k}")
    copies = new_k // old_k
    rows = tensor.reshape(1, old_k, per_point, *tensor.shape[1:])
    rows = rows.expand(copies, *rows.shape[1:]).clone()
    if head[1] == "reg" and head[3] == "bias":   # the offsets are the bias, in metres
        side = math.ceil(math.sqrt(copies))
        voxel = float(cfg.voxel_size)
        grid = [((i - (side - 1) / 2) * voxel, (j - (side - 1) / 2) * voxel)
                for i in range(side) for j in range(side)][:copies]
        rows[:, :, :2] += torch.tensor(grid, dtype=rows.dtype)[:, None, :]
    return rows.reshape(fresh.shape)


def load_weights(model: ODG, state: dict) -> None:
    """Load a checkpoint's state (compressed or not, grown where ``model`` is larger, see
    grow_state_dict) into ``model``, cast to the model's own dtypes."""
    own = model.state_dict()
    state = grow_state_dict(decompress_state(state), model)
    model.load_state_dict({k: v.to(own[k].dtype) if k in own else v for k, v in state.items()})


def load_model(path=None, preset: str = "odg_cpu", device="cpu", **overrides):
    """-> (model in eval mode on ``device``, config). ``path`` None: random weights of ``preset``."""
    if path is None:
        cfg = load_preset(preset, **overrides)
        model = ODG(cfg)
    else:
        payload = read_checkpoint(path)
        try:
            cfg = ModelConfig(**{**payload["config"], **overrides})
            model = ODG(cfg)
            load_weights(model, payload["model"])
        except (TypeError, ValueError, KeyError, RuntimeError) as error:
            raise CheckpointError(f"checkpoint {path} does not fit this version of odg_ros: "
                                  f"{_first_line(error)}") from error
    return model.to(device).eval(), cfg


class CheckpointError(ValueError):
    """A checkpoint that is missing, unreadable or does not fit the model code."""


def _first_line(error: BaseException, limit: int = 240) -> str:
    """The error on one line, cut at ``limit`` characters (state-dict errors list every key)."""
    text = " ".join(str(error).split())
    text = text if len(text) <= limit else text[:limit] + "..."
    return f"{type(error).__name__}: {text}"


def read_checkpoint(path) -> dict:
    """The payload of a checkpoint file ({"config", "model", ...}), or a CheckpointError that
    says in one line what is wrong with the file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as error:     # torch raises several kinds for truncated / foreign files
        raise CheckpointError(f"checkpoint {path} is not a readable checkpoint file "
                              f"(truncated or another format): {_first_line(error)}") from error
    if not isinstance(payload, dict) or not {"config", "model"} <= set(payload):
        raise CheckpointError(f"checkpoint {path} is not an odg_ros checkpoint (no config and "
                              "model entries)")
    return payload
