"""The image encoder (folded ResNet + FPN) in int8 on CPU: static quantization with PyTorch's
FX graph mode (``x86`` engine: fbgemm / oneDNN), per-channel symmetric int8 weights and
per-tensor uint8 activations.

The activation ranges come from a small side file, ``model/int8/<fingerprint>.json``, keyed by
a hash of the float encoder's weights: the range each activation observer settled on when the
encoder ran over training-world camera images (``python -m tools.calibrate_int8_encoder``).
Loading them instead of calibrating at node start keeps the start fast and every start's
arithmetic the same; the weights' scales are computed from the weights themselves at load.
Activations use all 8 bits on a CPU with VNNI (or AMX), whose products of 8-bit values sum
into int32; elsewhere the same ranges on 7 bits (``reduce_range``), so that the int16 sums of
those CPUs cannot saturate: correct there, coarser and slower. The stem convolution stays in
float32 (FLOAT_MODULES)."""
from __future__ import annotations

import copy
import hashlib
import json
import math
import warnings
from contextlib import contextmanager
from pathlib import Path

import torch
from torch import nn
from torch.ao.quantization import QConfig, QConfigMapping, get_default_qconfig_mapping
from torch.ao.quantization.observer import HistogramObserver, MinMaxObserver
from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx

from . import precision

ENGINE = "x86"
RANGES_DIR = "model/int8"
RANGES_FORMAT = 2
# kept in float32: the stem (3 input channels: int8 gains nothing there, and its error was
# the largest of any one layer's)
FLOAT_MODULES = ("backbone.conv1",)


class Encoder(nn.Module):
    """images [N, 3, H, W] -> the FPN's levels: the backbone then the neck, one module for FX."""

    def __init__(self, backbone: nn.Module, neck: nn.Module):
        super().__init__()
        self.backbone, self.neck = backbone, neck

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return self.neck(self.backbone(x))


class MissingRanges(ValueError):
    """No activation ranges for this encoder's weights."""


def int8_available() -> bool:
    """PyTorch here has the x86 quantized engine (a CPU build for x86-64)."""
    return ENGINE in torch.backends.quantized.supported_engines


def encoder_fingerprint(backbone: nn.Module, neck: nn.Module) -> str:
    """16 hex digits of a SHA-256 over the float encoder's parameters and buffers (names,
    shapes, float32 bytes): the ranges belong to these weights and to no others."""
    digest = hashlib.sha256()
    for prefix, module in (("backbone.", backbone), ("neck.", neck)):
        for name, tensor in sorted(module.state_dict().items()):
            t = tensor.detach().to("cpu", torch.float32).contiguous()
            digest.update(f"{prefix}{name}{tuple(t.shape)}".encode())
            digest.update(t.numpy().tobytes())
    return digest.hexdigest()[:16]


def _mapping(activation) -> QConfigMapping:
    """The x86 engine's per-channel symmetric int8 weights, ``activation`` observers, the
    float modules left out."""
    weight = get_default_qconfig_mapping(ENGINE).global_qconfig.weight
    mapping = get_default_qconfig_mapping(ENGINE).set_global(
        QConfig(activation=activation, weight=weight))
    for name in FLOAT_MODULES:
        mapping = mapping.set_module_name(name, None)
    return mapping


def _calibration_mapping() -> QConfigMapping:
    """Histogram activation observers over all 8 bits."""
    return _mapping(HistogramObserver.with_args(reduce_range=False))


def _fixed_range_mapping(reduce_range: bool) -> QConfigMapping:
    """Min/max activation observers whose ranges are then set from the side file (a histogram
    observer's chosen range gives the same scale and zero point); ``reduce_range``: 7 bits
    over the same range."""
    return _mapping(MinMaxObserver.with_args(reduce_range=reduce_range))


def _activation_observers(prepared: nn.Module) -> dict[str, nn.Module]:
    return {name: m for name, m in prepared.named_modules()
            if isinstance(m, (HistogramObserver, MinMaxObserver))}


def calibrate(folded_backbone: nn.Module, neck: nn.Module, batches: list[torch.Tensor],
              fingerprint: str, progress=None) -> dict:
    """Run the float encoder (the step's folded, channels-last modules) over ``batches``
    (normalised images [N, 3, H, W]) with histogram observers -> the side file's content:
    each activation observer's chosen [min, max]."""
    with _quiet():
        prepared = prepare_fx(Encoder(copy.deepcopy(folded_backbone), copy.deepcopy(neck)).eval(),
                              _calibration_mapping(), (batches[0],))
    images = 0
    with torch.no_grad():
        for x in (progress or (lambda items: items))(batches):
            prepared(x.contiguous(memory_format=torch.channels_last))
            images += len(x)
    ranges = {}
    for name, observer in _activation_observers(prepared).items():
        if observer.min_val.numel() == 0 or observer.histogram.sum() == 0:
            raise RuntimeError(f"activation observer {name} saw no data")
        low, high = observer._non_linear_param_search()     # the range its qparams use
        ranges[name] = [float(low), float(high)]
    return {"format": RANGES_FORMAT, "engine": ENGINE, "fingerprint": fingerprint,
            "images": images, "ranges": ranges}


def ranges_path(fingerprint: str, root: Path | None = None) -> Path:
    """Where the side file of the encoder with ``fingerprint`` lives (``model/int8``)."""
    if root is not None:
        return Path(root) / f"{fingerprint}.json"
    from ..resources import resource_path
    relative = f"{RANGES_DIR}/{fingerprint}.json"
    try:
        return resource_path(relative)
    except FileNotFoundError:
        raise MissingRanges(
            f"int8-encoder: no activation ranges for this checkpoint's encoder ({relative}); "
            "make them with python -m tools.calibrate_int8_encoder --checkpoint CKPT "
            "--data TRAINING_INFOS, or use precision fp32 / bf16-encoder") from None


def load_ranges(path: Path, fingerprint: str) -> dict[str, list[float]]:
    """The side file's ranges, checked: its format, engine and fingerprint."""
    try:
        content = json.loads(Path(path).read_text())
    except (OSError, ValueError) as error:
        raise MissingRanges(f"int8-encoder: cannot read {path}: {error}") from None
    if content.get("format") != RANGES_FORMAT or content.get("engine") != ENGINE or \
            content.get("fingerprint") != fingerprint:
        raise MissingRanges(f"int8-encoder: {path} is not the ranges of this encoder "
                            f"(format {RANGES_FORMAT}, engine {ENGINE}, fingerprint "
                            f"{fingerprint} expected)")
    return content["ranges"]


def quantized_encoder(folded_backbone: nn.Module, neck: nn.Module,
                      ranges: dict[str, list[float]], example: torch.Tensor) -> nn.Module:
    """The int8 encoder: the step's folded channels-last float modules quantized with the
    side file's activation ranges. float32 images in, float32 levels out."""
    if not int8_available():
        raise ValueError(f"int8-encoder needs PyTorch's {ENGINE} quantized engine, which this "
                         "build lacks (an x86-64 CPU build has it)")
    torch.backends.quantized.engine = ENGINE
    # without VNNI the products of two 8-bit values could saturate an int16 sum: 7 bits there
    with _quiet():
        mapping = _fixed_range_mapping(reduce_range=not precision.cpu_has_vnni())
        prepared = prepare_fx(Encoder(copy.deepcopy(folded_backbone), copy.deepcopy(neck)).eval(),
                              mapping, (example,))
    observers = _activation_observers(prepared)
    if set(observers) != set(ranges):
        raise MissingRanges("int8-encoder: the side file's observers "
                            f"({len(ranges)}) do not match this encoder's graph "
                            f"({len(observers)}); recalibrate")
    for name, observer in observers.items():
        low, high = ranges[name]
        if not (math.isfinite(low) and math.isfinite(high) and low <= high):
            raise MissingRanges(f"int8-encoder: activation range {name} [{low}, {high}] "
                                "is not a finite range")
        observer.min_val = torch.tensor(low)
        observer.max_val = torch.tensor(high)
    with _quiet():
        return convert_fx(prepared).eval()


@contextmanager
def _quiet():
    """torch.ao.quantization's deprecation notices (its FX flow is moving to torchao; this
    PyTorch still ships and runs it) would fill the node's log at each start."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        warnings.filterwarnings("ignore", message=".*reduce_range will be deprecated.*")
        warnings.filterwarnings("ignore", message=".*quantize_per_tensor.*deprecated.*")
        yield
