"""Inference precision: fp32, or bf16 / fp16 autocast (geometry stays float32 inside, see
sampling.full_precision). Shared by the benchmark, the sweep and the online predictor."""
from __future__ import annotations

from contextlib import nullcontext

import torch

PRECISIONS = ("fp32", "bf16", "fp16")


def precision_context(precision: str, device):
    """fp32: nothing; bf16 / fp16: autocast on the device (fp16 only on CUDA)."""
    device_type = torch.device(device).type
    if precision not in PRECISIONS:
        raise ValueError(f"precision {precision!r}: expected one of {PRECISIONS}")
    if precision == "fp32":
        return nullcontext()
    if precision == "fp16" and device_type != "cuda":
        raise ValueError("fp16 autocast is for CUDA; use bf16 on CPU")
    dtype = torch.bfloat16 if precision == "bf16" else torch.float16
    return torch.autocast(device_type=device_type, dtype=dtype)
