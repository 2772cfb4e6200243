"""Census of one training step: the ATen ops it launches and the host syncs it makes, by phase
and by source line.

An op is counted where it reaches a backend (a TorchDispatchMode, below autograd), so on CUDA
one op is roughly one kernel launch (views, which launch nothing, are not counted). A host sync is an op whose result size or value the host
must wait for: ``.item()`` / ``bool()`` / ``float()`` reads, ``nonzero``, boolean-mask indexing,
``unique``, ``bincount``, ``repeat_interleave`` without ``output_size``, a copy to the CPU, and
``.numpy()`` / ``.tolist()``. With ``cuda_paths`` the step takes the code paths a CUDA run takes
(nearest neighbours on the device, fused AdamW) and every op of the CPU run counts as if its
tensors lived on the GPU, so the census of a GPU run can be taken on a CPU. What a CUDA run
keeps on the host is told apart: ops drawing from a CPU generator (a CUDA op cannot), the
batch's host keys (``batch.HOST_KEYS``), and whatever is computed from these alone; ``.to()``
of such a tensor is its upload, a host sync unless ``non_blocking`` (torch waits for the
stream after a blocking copy to the GPU).
"""
from __future__ import annotations

import collections
import linecache
import sys
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from ..data.batch import HOST_KEYS, tensors_in

aten = torch.ops.aten
PHASES = ("data", "forward", "losses", "render", "backward", "optimizer")
_PACKAGE = str(Path(__file__).resolve().parents[1]) + "/"
_THIS_FILE = str(Path(__file__).resolve())
# Trainer methods, outermost first, and the phase their ops belong to.
_TRAINER_PHASES = {"_load_batch": "data", "_forward": "forward", "_losses": "losses",
                   "_backward": "backward", "_optimizer_step": "optimizer"}
_RENDER_FILES = ("render/", "losses/render_loss.py")

# Ops whose output size or value the host needs before it can go on.
_ALWAYS_SYNC = {aten._local_scalar_dense.default, aten.nonzero.default, aten.masked_select.default,
                aten.equal.default, aten.is_nonzero.default, aten._unique.default,
                aten._unique2.default, aten.unique_dim.default, aten.unique_consecutive.default,
                aten.bincount.default}
_HOST_READS = ("numpy", "tolist")


def _draws_on_host(kwargs) -> bool:
    generator = kwargs.get("generator")
    return generator is not None and generator.device.type == "cpu"


def _is_sync(func, args, kwargs, device_type: str | None) -> bool:
    tensors = [a for a in args if isinstance(a, torch.Tensor)]
    on_device = device_type is None or any(t.device.type == device_type for t in tensors)
    if func in _ALWAYS_SYNC:
        return on_device
    if func in (aten.repeat_interleave.Tensor, aten.repeat_interleave.self_Tensor):
        return on_device and kwargs.get("output_size") is None
    if func in (aten.index.Tensor, aten.index_put.default, aten.index_put_.default,
                aten._index_put_impl_.default):
        indices = args[1] if len(args) > 1 else ()
        return on_device and any(i is not None and i.dtype in (torch.bool, torch.uint8)
                                 for i in indices)
    if func in (aten._to_copy.default, aten.copy_.default) and device_type is not None:
        source = args[1] if func is aten.copy_.default else args[0]
        target = args[0].device if func is aten.copy_.default else kwargs.get("device")
        return (source.device.type == device_type and target is not None
                and torch.device(target).type == "cpu")
    return False


def _where() -> tuple[str, str]:
    """(phase, source line) of the op being dispatched, from the Python stack."""
    frame, line, phase, render = sys._getframe(2), None, "other", False
    while frame is not None:
        filename = frame.f_code.co_filename
        if filename.startswith(_PACKAGE) and filename != _THIS_FILE:
            relative = filename[len(_PACKAGE):]
            if line is None:
                code = linecache.getline(filename, frame.f_lineno).strip()
                line = f"{relative}:{frame.f_lineno} {code}"
            render = render or relative.startswith(_RENDER_FILES)
            if frame.f_code.co_name in _TRAINER_PHASES and relative == "train/trainer.py":
                phase = _TRAINER_PHASES[frame.f_code.co_name]
                break
        frame = frame.f_back
    if phase == "losses" and render:
        phase = "render"
    return phase, line or "(outside odg_ros)"


@dataclass
class Census:
    """Counts per (phase, source line); ``steps`` divides them into per-step numbers."""
    ops: collections.Counter = field(default_factory=collections.Counter)
    syncs: collections.Counter = field(default_factory=collections.Counter)
    steps: int = 1

    def per_step(self, counter: collections.Counter, phase: str | None = None) -> float:
        return sum(n for (p, _), n in counter.items() if phase in (None, p)) / self.steps

    def by_line(self, counter: collections.Counter, top: int) -> list[tuple[float, str, str]]:
        return [(n / self.steps, phase, line) for (phase, line), n in counter.most_common(top)]

    def report(self, top: int = 12) -> str:
        rows = [f"{'phase':10s} {'ops/step':>10s} {'syncs/step':>11s}"]
        for phase in PHASES + ("other",):
            ops, syncs = self.per_step(self.ops, phase), self.per_step(self.syncs, phase)
            if ops or syncs:
                rows.append(f"{phase:10s} {ops:10,.0f} {syncs:11,.0f}")
        rows.append(f"{'total':10s} {self.per_step(self.ops):10,.0f} "
                    f"{self.per_step(self.syncs):11,.0f}")
        for title, counter in (("host syncs", self.syncs), ("launched ops", self.ops)):
            rows.append(f"\n{title} per step by source line (top {top}):")
            rows += [f"{n:9,.0f}  {phase:9s} {line}" for n, phase, line in
                     self.by_line(counter, top)]
        return "\n".join(rows)


def _storage(t: torch.Tensor) -> int:
    """Identity of a strided tensor's memory (shared by its views); -1 for sparse ones."""
    return t.untyped_storage().data_ptr() if t.layout == torch.strided else -1


class CensusMode(TorchDispatchMode):
    """Counts ops and host syncs into ``census``; ``device_type`` None counts every tensor as
    a device tensor (the CUDA paths on a CPU), else only tensors of that device type sync.
    ``host_tensors``: tensors that a CUDA run keeps on the host (the optimizer's step counters).
    What is computed from host tensors alone, and what ``.cpu()`` returns, is on the host too:
    its ops are neither launches nor syncs (with the CUDA paths forced, ``.cpu()`` is the sync)."""

    def __init__(self, census: Census, device_type: str | None, host_tensors=()):
        super().__init__()
        self.census, self.device_type = census, device_type
        self._host: set[int] = set()
        self._kept = []             # host storages stay alive: their addresses are not reused
        for t in host_tensors:
            self._mark_host(t)
        self._uploading = False
        self._originals = {name: getattr(torch.Tensor, name)
                           for name in _HOST_READS + ("cpu", "to")}

    def _mark_host(self, t: torch.Tensor) -> None:
        if t.layout != torch.strided:
            return
        self._host.add(_storage(t))
        self._kept.append(t.untyped_storage())

    def _on_host(self, t: torch.Tensor) -> bool:
        return (self.device_type is not None and t.device.type != self.device_type) or \
            _storage(t) in self._host

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        tensors = [t for a in list(args) + list(kwargs.values())
                   for t in (a if isinstance(a, (list, tuple)) else (a,))
                   if isinstance(t, torch.Tensor)]
        on_host = all(self._on_host(t) for t in tensors) if tensors else _draws_on_host(kwargs)
        if on_host and not self._uploading:
            out = func(*args, **kwargs)
            if self.device_type is None:
                for t in (out if isinstance(out, (list, tuple)) else (out,)):
                    if isinstance(t, torch.Tensor):
                        self._mark_host(t)
            return out
        sync = _is_sync(func, args, kwargs, self.device_type)
        if sync or not func.is_view:              # a view launches no kernel
            where = _where()
            self.census.ops[where] += 1
            self.census.syncs[where] += sync
        return func(*args, **kwargs)

    def __enter__(self):
        for name in _HOST_READS:
            def counted(tensor, *args, _original=self._originals[name], **kwargs):
                if not self._on_host(tensor):
                    self.census.syncs[_where()] += 1
                return _original(tensor, *args, **kwargs)
            setattr(torch.Tensor, name, counted)

        def to_host(tensor, *args, _original=self._originals["cpu"], **kwargs):
            on_host = self._on_host(tensor)
            out = _original(tensor, *args, **kwargs)
            if not on_host and self.device_type is None:     # a no-op on the CPU: count it
                self.census.syncs[_where()] += 1
                self._mark_host(out)
            return out
        torch.Tensor.cpu = to_host

        def upload(tensor, *args, _original=self._originals["to"], **kwargs):
            out = _original(tensor, *args, **kwargs)
            device, _, non_blocking, _ = torch._C._nn._parse_to(*args, **kwargs)
            if self.device_type is None and device is not None and self._on_host(tensor):
                self._uploading = True                 # the copy is a launch; its result is
                try:                                   # a device tensor
                    out = out.clone()
                finally:
                    self._uploading = False
                # a blocking upload waits for the stream (torch synchronises after the copy)
                self.census.syncs[_where()] += not non_blocking
            return out
        torch.Tensor.to = upload
        return super().__enter__()

    def __exit__(self, *exc):
        for name, original in self._originals.items():
            setattr(torch.Tensor, name, original)
        return super().__exit__(*exc)


def force_cuda_paths(trainer) -> None:
    """The code paths a CUDA run takes, on whatever device ``trainer`` runs."""
    trainer.criterion.nn_method = "cdist"
    for group in trainer.optimizer.param_groups:
        group["fused"], group["foreach"] = True, False


def optimizer_host_tensors(optimizer) -> list[torch.Tensor]:
    """The step counters that a CUDA run keeps on the host (all but fused / capturable AdamW)."""
    keep_on_device = any(g.get("fused") or g.get("capturable") for g in optimizer.param_groups)
    if keep_on_device:
        return []
    return [state["step"] for state in optimizer.state.values() if "step" in state]


def batch_host_tensors(batch: dict) -> list[torch.Tensor]:
    """The tensors of a batch that stay on the host in a CUDA run (``batch.HOST_KEYS``)."""
    return [t for key in HOST_KEYS for t in tensors_in(batch.get(key))]


def census_of_steps(trainer, batches, cuda_paths: bool) -> Census:
    """Census of ``trainer.train_step`` over ``batches`` (one warm-up step first, not counted)."""
    if cuda_paths:
        force_cuda_paths(trainer)
    trainer.train_step(batches[0])
    census = Census(steps=len(batches) - 1)
    device_type = None if cuda_paths else trainer.device.type
    host = optimizer_host_tensors(trainer.optimizer) + \
        [t for batch in batches[1:] for t in batch_host_tensors(batch)] if cuda_paths else ()
    with CensusMode(census, device_type, host):
        for batch in batches[1:]:
            trainer.train_step(batch)
    return census
