"""Inference device and precision: fp32, bf16 / fp16 autocast (geometry stays float32 inside,
see sampling.full_precision), or bf16-encoder: the image encoder (ResNet + FPN, most of the
CPU step's arithmetic) in bf16 and the decoder in fp32, or int8-encoder: that encoder in static
int8 on CPU (network/int8_encoder.py), the decoder in fp32. Shared by the commands, the node, the
benchmark, the sweep and the online predictor."""
from __future__ import annotations

import copy
from contextlib import nullcontext
from functools import lru_cache

import torch
from torch import nn

PRECISIONS = ("fp32", "bf16", "bf16-encoder", "int8-encoder", "fp16")
# the node's precision parameter: one of those, or auto (resolve_precision)
NODE_PRECISIONS = ("auto",) + PRECISIONS


def resolve_device(name: str) -> str:
    """auto (cuda where there is one, else cpu), cpu, cuda or cuda:N as a torch device name;
    a CUDA device asked for where there is none is a ValueError."""
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} requested but CUDA is not available")
    if name != "cpu" and not name.startswith("cuda"):
        raise ValueError(f"device must be auto, cpu, cuda or cuda:N, not {name!r}")
    return name


def precision_context(precision: str, device):
    """The decoder's context: fp32, bf16-encoder and int8-encoder nothing; bf16 / fp16 autocast
    on the device (fp16 only on CUDA; int8-encoder only on CPU)."""
    device_type = torch.device(device).type
    if precision not in PRECISIONS:
        raise ValueError(f"precision {precision!r}: expected one of {PRECISIONS}")
    if precision == "fp16" and device_type != "cuda":
        raise ValueError("fp16 autocast is for CUDA; use bf16 on CPU")
    if precision == "int8-encoder":
        if device_type != "cpu":
            raise ValueError("int8-encoder is for CPU (PyTorch's x86 quantized kernels); use "
                             "fp32, bf16 or fp16 on CUDA")
        from .int8_encoder import ENGINE, int8_available
        if not int8_available():
            raise ValueError(f"int8-encoder needs PyTorch's {ENGINE} quantized engine, which "
                             "this build lacks")
    dtype = decoder_half_dtype(precision)
    if dtype is None:
        return nullcontext()
    return torch.autocast(device_type=device_type, dtype=dtype)


def resolve_precision(precision: str, device) -> str:
    """The node's ``precision`` parameter -> the precision it runs. ``auto``: bf16-encoder on
    a CPU with native bf16 kernels (AVX512-BF16 or AMX: the encoder about twice as fast; the
    shipped model's mIoU and RayIoU up by 0.03 and 0.08 and its box mAP down by 0.04 on the
    held-out split, where a bf16 decoder loses 0.46 box mAP: docs/node.md), fp32 everywhere
    else (a CPU without them, where bf16 is emulated and several times slower; CUDA). Others
    pass through, checked."""
    if precision == "auto":
        native = torch.device(device).type == "cpu" and cpu_has_native_bf16()
        return "bf16-encoder" if native else "fp32"
    precision_context(precision, device)              # an unknown / unusable one fails here
    return precision


def half_dtype(precision: str) -> torch.dtype | None:
    """The image encoder's half dtype: bf16 / bf16-encoder / fp16 -> the torch dtype; fp32 ->
    None."""
    return {"bf16": torch.bfloat16, "bf16-encoder": torch.bfloat16,
            "fp16": torch.float16}.get(precision)


def decoder_half_dtype(precision: str) -> torch.dtype | None:
    """The decoder's: bf16 / fp16 -> the torch dtype; fp32, bf16-encoder, int8-encoder ->
    None."""
    return {"bf16": torch.bfloat16, "fp16": torch.float16}.get(precision)


def with_half_matrix_weights(module: nn.Module, dtype: torch.dtype) -> nn.Module:
    """A copy of ``module`` whose Linear and convolution weights and biases are stored in
    ``dtype``; norms and other parameters stay float32. Under autocast this computes what
    float32 weights compute (autocast casts exactly these to ``dtype`` before each matrix
    product) without the per-call weight casts."""
    half = copy.deepcopy(module)
    for m in half.modules():
        if isinstance(m, (nn.Linear, nn.Conv1d, nn.Conv2d, nn.Conv3d)):
            m.to(dtype)
    return half


def cpu_has_native_bf16() -> bool:
    """This CPU has bf16 instructions (AVX512-BF16 or AMX, /proc/cpuinfo's flags) and
    PyTorch's oneDNN has bf16 kernels for it. oneDNN alone also says yes on an AVX-512 CPU
    without them, where it emulates bf16; a CPU whose flags cannot be read counts as
    without (only Linux has /proc/cpuinfo)."""
    try:
        if not torch.ops.mkldnn._is_mkldnn_bf16_supported():
            return False
    except (AttributeError, RuntimeError):   # a build without oneDNN
        return False
    return bool(_cpu_flags() & {"avx512_bf16", "amx_bf16"})


def cpu_has_vnni() -> bool:
    """This CPU multiplies 8-bit values and sums the products into int32 in one instruction
    (AVX512-VNNI, AVX-VNNI or AMX); without it PyTorch's int8 kernels sum pairs in int16."""
    return bool(_cpu_flags() & {"avx512_vnni", "avx_vnni", "amx_int8"})


@lru_cache(maxsize=1)
def _cpu_flags() -> frozenset[str]:
    """The CPU's feature flags (the first core's, Linux), or none."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("flags"):
                    return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


def slow_precision_warning(precision: str, device) -> str | None:
    """Why ``precision`` will be slower than fp32 on ``device``, or None. bf16 autocast pays on
    a CPU with native bf16 kernels; without them every convolution and matrix product converts
    and emulates (odg_cpu on an AVX2-only EPYC: 2,270 ms a step against 327 ms in fp32)."""
    if precision in ("bf16", "bf16-encoder") and torch.device(device).type == "cpu" and \
            not cpu_has_native_bf16():
        return (f"{precision} on this CPU has no native bf16 kernels (no AVX512-BF16 / AMX): "
                "expect it several times slower than fp32; use precision fp32 (or auto) here")
    if precision == "int8-encoder" and torch.device(device).type == "cpu" and \
            not cpu_has_vnni():
        return ("int8-encoder on this CPU has no VNNI int8 dot products (AVX512-VNNI, "
                "AVX-VNNI or AMX): its activations get 7 bits instead of 8 (coarser), and "
                "expect little or no gain over fp32")
    return None
