"""The online step compiled ahead of time (AOTInductor) into one ``.pt2`` file, so that a
node restart loads it in about a second instead of compiling the step again.

``odg export --aoti FILE.pt2`` exports ``OnlineStep`` over a full ring (``torch.export``),
compiles it with AOTInductor and packages the shared library, the weights and a signature
(``odg_step.json``: torch version, device type, precision, history length, the model
configuration and a hash of the weights). The node (parameter ``compiled_step``) reads the
signature first and refuses, in one line, an artifact built for anything else: the weights
and the thresholds are constants inside it, so a stale one would silently run the wrong model.

The exported function takes the ring's memory as inputs and writes the newest frame into
it in place (an artifact holds no state but its constants):

    images uint8 [N, H, W, 3], packed float32 [n], ring_0..ring_{L-1} (written in place)
      -> labels, confidence, boxes, score, label, valid, observed (as ``OnlineStep``)
"""
from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.export.pt2_archive.constants import AOTINDUCTOR_DIR

from .step import OnlineStep
from ..network.visibility import DEFAULT_MIN_CLEAR

FORMAT = "odg-online-step-2"    # 2: the observed output and the visibility geometry
SIGNATURE_FILE = "odg_step.json"
# what a signature holds, in the order a mismatch is reported
SIGNATURE_KEYS = ("format", "torch", "device", "precision", "capacity", "visibility",
                  "visibility_min_clear", "config", "weights")


class StaleArtifact(ValueError):
    """A compiled step built for another model, configuration, device or torch."""


class RingInputStep(nn.Module):
    """``OnlineStep`` with its ring memory passed in (and written in place)."""

    def __init__(self, step: OnlineStep):
        super().__init__()
        self.step = step

    def forward(self, images: torch.Tensor, packed: torch.Tensor, *ring: torch.Tensor):
        self.step.ring.use_memory(ring)
        return self.step(images, packed)


def weights_hash(model: nn.Module) -> str:
    """sha256 over the names, dtypes, shapes and bytes of the model's state."""
    digest = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        tensor = tensor.detach().cpu().contiguous()
        digest.update(f"{name} {tensor.dtype} {tuple(tensor.shape)}".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def step_signature(model: nn.Module, cfg, capacity: int, device, precision: str,
                   visibility: bool = True, min_clear: float = DEFAULT_MIN_CLEAR) -> dict:
    """What a compiled step is valid for (compared key by key when it is loaded)."""
    return {"format": FORMAT, "torch": torch.__version__, "device": torch.device(device).type,
            "precision": precision, "capacity": int(capacity), "visibility": bool(visibility),
            "visibility_min_clear": float(min_clear) if visibility else None,
            "config": json.loads(json.dumps(cfg.to_dict())), "weights": weights_hash(model)}


def export_artifact(model: nn.Module, cfg, path, capacity: int | None = None, device="cpu",
                    precision: str = "fp32", visibility: bool = True,
                    min_clear: float = DEFAULT_MIN_CLEAR) -> tuple[Path, dict]:
    """Compile the online step over a ring of ``capacity`` (default: the model's frames) into
    ``path`` (.pt2) -> (the path, its signature)."""
    from torch.export.pt2_archive._package import package_pt2
    path = Path(path)
    if path.suffix != ".pt2":
        raise ValueError(f"{path}: a compiled step is a .pt2 file")
    k = cfg.num_frames if capacity is None else int(capacity)
    model = model.to(device).eval()
    step = OnlineStep(model, cfg, k, device, precision, visibility=visibility,
                      min_clear=min_clear).eval()
    H, W = cfg.image_size
    images = torch.zeros(cfg.num_cams, H, W, 3, dtype=torch.uint8, device=device)
    packed = torch.zeros(step.layout.size)
    step.layout.pack(packed.numpy(), 0.0, np.broadcast_to(np.eye(4), (k, 4, 4)), 0.0, 0, 0)
    example = (images, packed.to(device), *step.ring.memory)
    with torch.no_grad():
        exported = torch.export.export(RingInputStep(step).eval(), example, strict=False)
        files = torch._inductor.aot_compile(exported.module(check_guards=False), example,
                                            options={"aot_inductor.package": True})
    signature = step_signature(model, cfg, k, device, precision, visibility, min_clear)
    package_pt2(str(path), aoti_files={"model": files},
                extra_files={SIGNATURE_FILE: json.dumps(signature)})
    return path, signature


def read_signature(path) -> dict:
    """The signature packaged in a compiled step, without loading its code."""
    path = Path(path)
    if not path.is_file():
        raise StaleArtifact(f"compiled step {path}: no such file")
    try:
        with zipfile.ZipFile(path) as archive:
            names = [n for n in archive.namelist() if n.endswith(f"extra/{SIGNATURE_FILE}")]
            if not names:
                raise StaleArtifact(f"compiled step {path}: no {SIGNATURE_FILE} in it (not "
                                    f"written by odg export --aoti)")
            return json.loads(archive.read(names[0]))
    except (zipfile.BadZipFile, json.JSONDecodeError, UnicodeDecodeError) as error:
        raise StaleArtifact(f"compiled step {path}: unreadable ({error})") from error


def check_signature(found: dict, expected: dict, path) -> None:
    """StaleArtifact naming the first thing ``found`` was built for that differs."""
    for key in SIGNATURE_KEYS:
        have, want = found.get(key), expected[key]
        if have == want:
            continue
        if key == "config" and isinstance(have, dict):
            field = next(f for f in sorted(set(have) | set(want)) if have.get(f) != want.get(f))
            have, want, key = have.get(field), want.get(field), f"config {field}"
        elif key == "weights":                     # hashes: another checkpoint
            have, want = f"{str(have)[:12]} (another checkpoint)", want[:12]
        raise StaleArtifact(f"compiled step {path} was built for {key} {have}, this node runs "
                            f"{want}: rebuild it with odg export --aoti, or leave "
                            f"compiled_step empty to compile at start-up")


def load_artifact(path, expected: dict, for_cuda_graph: bool = False):
    """The compiled step at ``path`` after its signature matched ``expected`` -> a callable
    (images, packed, *ring) -> the step's outputs (the ring written in place).
    for_cuda_graph: loaded single-threaded, without the runner's thread synchronisation,
    which conflicts with a CUDA graph capture (torch's note on ``run_single_threaded``); its
    kernels run on the current stream, as the capture needs."""
    check_signature(read_signature(path), expected, path)
    with zipfile.ZipFile(path) as archive:   # read_signature opened it: a valid archive
        code = [n for n in archive.namelist() if f"/{AOTINDUCTOR_DIR}" in n]
    if not code:   # torch 2.11's loader crashes the process on a package without a model
        raise StaleArtifact(f"compiled step {path} does not load: it holds no compiled "
                            "model (not written by odg export --aoti)")
    try:
        return torch._inductor.aoti_load_package(str(path),
                                                 run_single_threaded=for_cuda_graph)
    except RuntimeError as error:
        raise StaleArtifact(f"compiled step {path} does not load: "
                            f"{' '.join(str(error).split())[:200]}") from error
