"""Moving tensors to the device without making the host wait: pinned uploads, and constants
made once per device (a constant made anew from Python values in every step is a copy from
pageable memory that the host waits for on CUDA)."""
from __future__ import annotations

import torch


def upload(tensor: torch.Tensor, device, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``tensor`` on ``device`` (as ``dtype``), queued without making the host wait: a copy
    from pageable host memory would wait for the stream, so a host tensor is pinned first."""
    if dtype is not None:
        tensor = tensor.to(dtype)                                   # where it is
    if stages_in_pinned_memory(tensor, device):
        tensor = tensor.pin_memory()
    return tensor.to(device, non_blocking=True)


def stages_in_pinned_memory(tensor: torch.Tensor, device) -> bool:
    """Whether ``upload`` copies ``tensor`` to pinned memory before sending it to ``device``:
    a pageable host tensor bound for a CUDA device. (The census of a CUDA step taken on the
    CPU answers this for the tensors it counts as on the host.)"""
    return (torch.device(device).type == "cuda" and tensor.device.type == "cpu"
            and not tensor.is_pinned())


_CONSTANTS: dict = {}


def device_constant(values, device, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``torch.tensor(values, dtype=dtype)`` on ``device``, made once per process and device
    and then reused: made anew in every step, a constant from Python values is a copy from
    pageable memory that the host waits for on CUDA. The first call's copy is blocking, so the
    constant is complete for every stream that reads it later. Never modify it in place."""
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    key = (_frozen(values), device, dtype)
    constant = _CONSTANTS.get(key)
    if constant is None:
        constant = _CONSTANTS[key] = torch.tensor(values, dtype=dtype, device=device)
    return constant


def _frozen(values):
    """``values`` with every list a tuple (a dictionary key)."""
    if isinstance(values, (list, tuple)):
        return tuple(_frozen(v) for v in values)
    return values
