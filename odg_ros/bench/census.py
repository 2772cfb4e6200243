"""Census of one training step: the ATen ops it launches and the host waits it makes, by phase
and by source line. The phases are the ranges the step marks (``training_phases``); an op
outside every phase is "other". Profiler ranges launch nothing and are not counted.

An op is counted where it reaches a backend (a TorchDispatchMode, below autograd), so on CUDA
one op is roughly one kernel launch (views, which launch nothing, are not counted). A host
wait is anything the host must wait for the device at, of four kinds (``WAIT_KINDS``):

* **read**: a value comes to the host: ``.item()``, ``bool()`` / ``float()`` / ``int()`` of a
  tensor, ``.tolist()``, ``.numpy()``, ``allclose``, ``equal``, ``histc`` (its range);
* **download**: a copy to host memory: ``.cpu()``, ``.to("cpu")``, ``copy_`` into a host tensor;
* **shape**: an output whose size depends on the data: ``nonzero`` (``argwhere``, one-argument
  ``where``), ``masked_select``, boolean-mask indexing, ``unique*``, ``bincount``,
  ``repeat_interleave`` without ``output_size``;
* **upload**: a copy from host memory that torch makes wait for the stream: a fresh tensor of
  at least one dimension made on the device (``torch.tensor(data, device=...)``,
  ``x.new_tensor(list)``, ``torch.as_tensor`` of a list or array: torch copies it from
  pageable memory, then synchronises), a host tensor moved to the device without
  ``non_blocking`` or from unpinned memory (``.to()``, ``copy_``), and a host tensor of at least
  one dimension given to an op on the device (an implicit copy). 0-dim host tensors are not
  counted: device ops take them as scalars.

``cuda_paths``: the step takes the code paths a CUDA run takes (nearest neighbours on the
device, fused AdamW) and every tensor counts as a device tensor, except what a CUDA run keeps
on the host: ops drawing from a CPU generator (a CUDA op cannot), the batch's host keys
(``batch.HOST_KEYS``), the optimizer's host step counters, what ``.cpu()`` returns, and
whatever is computed from these alone. So the census of a GPU run is taken on a CPU. Two
things a CPU run cannot see directly are inferred:

* where a fresh tensor (``aten.lift_fresh``: ``torch.tensor``, ``new_tensor``, ``as_tensor``,
  ``from_numpy``) is made: where it is first used. If it first meets a device tensor in an op,
  a CUDA run made it on the device (an upload); if it meets host data or is moved by ``.to()``,
  it was made on the host;
* pinned memory: ``pin_memory()`` marks a host copy as pinned, and ``transfer.upload`` pins as on
  CUDA. The training device is the CPU here too, so ``.to(d)`` with a ``torch.device`` moves to
  the device; only ``"cpu"`` spelt as a string names the host.
"""
from __future__ import annotations

import collections
import contextlib
import functools
import linecache
import sys
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from .. import transfer
from ..data.batch import HOST_KEYS, tensors_in
from ..training_phases import PHASES, PREFIX

aten = torch.ops.aten
WAIT_KINDS = ("read", "download", "shape", "upload")
_PACKAGE = str(Path(__file__).resolve().parents[1]) + "/"
# files whose lines a wait is never attributed to: the census and its stand-ins
_OWN_FILES = {str(Path(__file__).resolve()),
              str(Path(__file__).resolve().with_name("gsplat_stand_in.py"))}
# the ranges the training step opens and closes around its phases (training_phases.py)
_PHASE_ENTER = torch.ops.profiler._record_function_enter_new.default
_PHASE_EXIT = torch.ops.profiler._record_function_exit._RecordFunction

# Ops whose output size or value the host needs before it can go on, by kind.
_READS = {aten._local_scalar_dense.default, aten.is_nonzero.default, aten.equal.default,
          aten.allclose.default, aten.histc.default}
_SHAPES = {aten.nonzero.default, aten.masked_select.default, aten._unique.default,
           aten._unique2.default, aten.unique_dim.default, aten.unique_consecutive.default,
           aten.unique_dim_consecutive.default, aten.bincount.default}
_FRESH = {aten.lift_fresh.default, aten.lift_fresh_copy.default}
_HOST_READS = ("numpy", "tolist")


def _draws_on_host(kwargs) -> bool:
    generator = kwargs.get("generator")
    return generator is not None and generator.device.type == "cpu"


def _shape_wait(func, args, kwargs) -> bool:
    """Whether the op's output size depends on the values of its (device) inputs."""
    if func in _SHAPES:
        return True
    if func in (aten.repeat_interleave.Tensor, aten.repeat_interleave.self_Tensor):
        return kwargs.get("output_size") is None
    if func in (aten.index.Tensor, aten.index_put.default, aten.index_put_.default,
                aten._index_put_impl_.default):
        indices = args[1] if len(args) > 1 else ()
        return any(i is not None and i.dtype in (torch.bool, torch.uint8) for i in indices)
    return False


def _source_line() -> str:
    """The innermost line of the package (outside the census) that the op being dispatched
    comes from."""
    frame = sys._getframe(2)
    while frame is not None:
        filename = frame.f_code.co_filename
        if filename.startswith(_PACKAGE) and filename not in _OWN_FILES:
            code = linecache.getline(filename, frame.f_lineno).strip()
            return f"{filename[len(_PACKAGE):]}:{frame.f_lineno} {code}"
        frame = frame.f_back
    return "(outside odg_ros)"


@dataclass
class Census:
    """Counts per (phase, source line); ``steps`` divides them into per-step numbers.
    ``syncs`` counts every host wait, ``kinds`` the same waits by kind (``WAIT_KINDS``)."""
    ops: collections.Counter = field(default_factory=collections.Counter)
    syncs: collections.Counter = field(default_factory=collections.Counter)
    kinds: collections.Counter = field(default_factory=collections.Counter)
    steps: int = 1

    def per_step(self, counter: collections.Counter, phase: str | None = None) -> float:
        return sum(n for (p, _), n in counter.items() if phase in (None, p)) / self.steps

    def by_line(self, counter: collections.Counter, top: int) -> list[tuple[float, str, str]]:
        return [(n / self.steps, phase, line) for (phase, line), n in counter.most_common(top)]

    def waits_by_kind(self) -> dict[str, float]:
        return {kind: self.kinds[kind] / self.steps for kind in WAIT_KINDS}

    def report(self, top: int = 12) -> str:
        rows = [f"{'phase':10s} {'ops/step':>10s} {'waits/step':>11s}"]
        for phase in PHASES + ("other",):
            ops, syncs = self.per_step(self.ops, phase), self.per_step(self.syncs, phase)
            if ops or syncs:
                rows.append(f"{phase:10s} {ops:10,.0f} {syncs:11,.0f}")
        rows.append(f"{'total':10s} {self.per_step(self.ops):10,.0f} "
                    f"{self.per_step(self.syncs):11,.0f}")
        rows.append("host waits per step by kind: " + ", ".join(
            f"{kind} {n:g}" for kind, n in self.waits_by_kind().items()))
        for title, counter in (("host waits", self.syncs), ("launched ops", self.ops)):
            rows.append(f"\n{title} per step by source line (top {top}):")
            rows += [f"{n:9,.0f}  {phase:9s} {line}" for n, phase, line in
                     self.by_line(counter, top)]
        return "\n".join(rows)


def _storage(t: torch.Tensor) -> int:
    """Identity of a strided tensor's memory, shared by its views (the storage object: the
    address of the data would be 0 for every empty one); -1 for sparse tensors."""
    return t.untyped_storage()._cdata if t.layout == torch.strided else -1


def _tensors(args, kwargs) -> list[torch.Tensor]:
    return [t for a in list(args) + list(kwargs.values())
            for t in (a if isinstance(a, (list, tuple)) else (a,)) if isinstance(t, torch.Tensor)]


def _names_the_host(args, kwargs) -> bool:
    """Whether ``.to()``'s arguments spell the host as a string ("cpu", "cpu:0")."""
    target = kwargs.get("device", args[0] if args else None)
    return isinstance(target, str) and target.startswith("cpu")


class CensusMode(TorchDispatchMode):
    """Counts ops and host waits into ``census`` (module docstring); ``device_type`` None
    counts every tensor as a device tensor (the CUDA paths on a CPU), else only tensors of
    that device type are on the device. ``host_tensors``: tensors that a CUDA run keeps on the
    host (the batch's targets, the optimizer's step counters).

    With the CUDA paths, each storage is of one kind: HOST (host data), FRESH (a fresh
    tensor, or computed from fresh tensors alone: made where it is first used) or, by
    default, DEVICE. DEVICE storages made by a factory (``torch.zeros``, ``arange``, ...) or
    from such alone are also "unused factories" until they meet other device data: one that
    meets host data (or is read) first was made on the host (a host op, no upload)."""

    HOST, FRESH, DEVICE = "host", "fresh", "device"

    def __init__(self, census: Census, device_type: str | None, host_tensors=()):
        super().__init__()
        self.census, self.device_type = census, device_type
        self._host: set[int] = set()
        self._fresh: dict[int, frozenset[int]] = {}   # storage -> the fresh tensors it is from
        self._made_on: dict[int, str] = {}            # fresh tensor -> HOST or DEVICE
        self._factory: set[int] = set()
        self._pinned: set[int] = set()
        self._kept = []             # marked storages stay alive: their addresses are not reused
        self._quiet = 0
        self._ranges: list[str | None] = []   # the phase of each open range (None: no phase)
        self.active = False
        for t in host_tensors:
            self._mark(t, self.HOST)
        self._originals = {name: getattr(torch.Tensor, name) for name in
                           _HOST_READS + ("cpu", "to", "pin_memory", "is_pinned")}
        self._stages = transfer.stages_in_pinned_memory

    # -------------------------------------------------------------- where tensors are
    def _mark(self, t: torch.Tensor, kind: str, roots: frozenset = frozenset()) -> None:
        storage = _storage(t)
        if storage == -1:
            return
        self._fresh.pop(storage, None)
        self._host.discard(storage)
        self._factory.discard(storage)
        if kind == self.HOST:
            self._host.add(storage)
        elif kind == self.FRESH:
            self._fresh[storage] = roots or frozenset({storage})
        self._kept.append(t.untyped_storage())

    def _mark_factory(self, out) -> None:
        for t in (out if isinstance(out, (list, tuple)) else (out,)):
            if isinstance(t, torch.Tensor) and _storage(t) != -1:
                self._factory.add(_storage(t))
                self._kept.append(t.untyped_storage())

    def _kind(self, t: torch.Tensor) -> str:
        if self.device_type is not None:
            return self.HOST if t.device.type != self.device_type else self.DEVICE
        storage = _storage(t)
        if storage in self._host:
            return self.HOST
        return self.FRESH if storage in self._fresh else self.DEVICE

    def _on_device(self, t: torch.Tensor) -> bool:
        """A device tensor that is not an unused factory (a read of it waits)."""
        return self._kind(t) == self.DEVICE and _storage(t) not in self._factory

    def _made_on_host(self, t: torch.Tensor) -> None:
        """A fresh tensor met host data or was moved by ``.to()``: it was made on the host."""
        for root in self._fresh.get(_storage(t), ()):
            self._made_on.setdefault(root, self.HOST)

    def _uploads_of(self, t: torch.Tensor, kind: str) -> int:
        """Waits for a host or fresh tensor ``t`` given to an op on the device."""
        if t.dim() == 0 or not t.numel():
            return 0                                # a scalar, passed by value; or empty
        if kind == self.HOST:
            return 1                                # an implicit copy of host data
        roots = self._fresh[_storage(t)]
        if any(self._made_on.get(root) == self.HOST for root in roots):
            return 1
        new = [root for root in roots if root not in self._made_on]
        for root in roots:
            self._made_on[root] = self.DEVICE
        self._mark(t, self.DEVICE)                  # made on the device: a device tensor
        return len(new)

    # -------------------------------------------------------------- phases
    def _range(self, func, args, kwargs):
        """A profiler range opened or closed (ranges nest: a range closes the innermost one
        open); a phase of the training step when it is one of ``training_phases``'. A range
        launches nothing and is not counted."""
        if func is _PHASE_ENTER:
            name = args[0]
            self._ranges.append(name[len(PREFIX):] if name.startswith(PREFIX) else None)
        elif func is _PHASE_EXIT and self._ranges:
            self._ranges.pop()
        return func(*args, **kwargs)

    def _where(self) -> tuple[str, str]:
        """(phase, source line) of the op being dispatched: the innermost phase open, "other"
        outside every phase."""
        phase = next((p for p in reversed(self._ranges) if p is not None), "other")
        return phase, _source_line()

    # -------------------------------------------------------------- counting
    def record(self, ops: int = 0, waits: int = 0, kind: str = "read") -> None:
        """Counts at the current source line while active (stand-ins of kernels that cannot
        run here)."""
        if not self.active:
            return
        self._add(self._where(), ops, [(kind, waits)] if waits else [])

    def _add(self, where, ops: int, waits) -> None:
        self.census.ops[where] += ops
        for kind, number in waits:
            if number:
                self.census.syncs[where] += number
                self.census.kinds[kind] += number

    @contextlib.contextmanager
    def uncounted(self):
        """Ops here are neither counted nor change where tensors are (stand-ins' values)."""
        self._quiet += 1
        try:
            yield
        finally:
            self._quiet -= 1

    def _count(self, func, waits=()) -> None:
        """One op (unless a view without waits: it launches no kernel) and its waits,
        (kind, number) pairs."""
        if any(number for _, number in waits) or not func.is_view:
            self._add(self._where(), 1, waits)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func.namespace == "profiler":
            return self._range(func, args, kwargs)
        if self._quiet:
            return func(*args, **kwargs)
        if func in _FRESH:
            return self._fresh_tensor(func, args, kwargs)
        if func is aten.copy_.default:
            return self._copy(func, args, kwargs)
        if func is aten._to_copy.default and self.device_type is not None:
            self._transfer(args[0], kwargs)
        tensors = _tensors(args, kwargs)
        kinds = [self._kind(t) for t in tensors]
        on_device = [t for t, k in zip(tensors, kinds) if k == self.DEVICE]
        factories_only = all(_storage(t) in self._factory for t in on_device)
        if on_device and factories_only and self.device_type is None and \
                (self.HOST in kinds or func in _READS):
            for t in on_device:                     # factories that were made on the host
                self._mark(t, self.HOST)
            kinds = [self._kind(t) for t in tensors]
            on_device = []
        if not on_device and (tensors or _draws_on_host(kwargs)):
            return self._on_host(func, args, kwargs, tensors, kinds)
        waits = [("upload", sum(self._uploads_of(t, k) for t, k in zip(tensors, kinds)
                                if k != self.DEVICE))]
        if func in _READS:
            waits.append(("read", 1))
        elif _shape_wait(func, args, kwargs):
            waits.append(("shape", 1))
        self._count(func, waits)
        out = func(*args, **kwargs)
        if self.device_type is None:
            if factories_only:
                self._mark_factory(out)
            else:
                for t in on_device:
                    self._factory.discard(_storage(t))
        return out

    def _transfer(self, source: torch.Tensor, kwargs) -> None:
        """On a real device: ``_to_copy`` between the host and the device."""
        target = kwargs.get("device")
        if target is None or torch.device(target).type == source.device.type:
            return
        if source.device.type == self.device_type:
            self._count(aten._to_copy.default, [("download", 1)])
        elif torch.device(target).type == self.device_type:
            pinned = source.is_pinned() and bool(kwargs.get("non_blocking"))
            self._count(aten._to_copy.default, [("upload", int(not pinned))])

    def _on_host(self, func, args, kwargs, tensors, kinds):
        """An op on host (or fresh) tensors alone: neither a launch nor a wait. Its result is
        host data if any input is (or it draws from a CPU generator), else fresh."""
        out = func(*args, **kwargs)
        if self.device_type is not None:
            return out
        from_host = self.HOST in kinds or not tensors
        fresh = [t for t, k in zip(tensors, kinds) if k == self.FRESH]
        if from_host:
            for t in fresh:
                if t.dim():
                    self._made_on_host(t)
        roots = frozenset().union(*(self._fresh[_storage(t)] for t in fresh))
        for t in (out if isinstance(out, (list, tuple)) else (out,)):
            if isinstance(t, torch.Tensor):
                self._mark(t, self.HOST if from_host else self.FRESH, roots)
        return out

    def _fresh_tensor(self, func, args, kwargs):
        out = func(*args, **kwargs)
        if self.device_type is None:
            self._mark(out, self.FRESH)              # where it is made: decided by its use
        elif out.device.type == self.device_type:    # made on the device (a CPU run: no copy)
            self._count(func, [("upload", int(out.dim() > 0 and self.device_type != "cpu"))])
        return out

    def _copy(self, func, args, kwargs):
        """``dst.copy_(src)``: an upload, a download, or an op on one side."""
        dst, src = args[0], args[1]
        non_blocking = bool(args[2]) if len(args) > 2 else bool(kwargs.get("non_blocking"))
        to_kind, from_kind = self._kind(dst), self._kind(src)
        if self.device_type is None:
            for t, k in ((dst, to_kind), (src, from_kind)):
                if k == self.DEVICE and _storage(t) in self._factory:
                    self._factory.discard(_storage(t))     # a factory written or read
            if to_kind == self.FRESH and from_kind == self.DEVICE:
                self._uploads_of(dst, to_kind)           # written on the device: made there
                to_kind = self.DEVICE
            if from_kind == self.FRESH:
                self._made_on_host(src)
        if to_kind != self.DEVICE and from_kind != self.DEVICE:
            return func(*args, **kwargs)            # host to host
        if to_kind == self.DEVICE and from_kind != self.DEVICE:
            pinned = _storage(src) in self._pinned or \
                (self.device_type is not None and src.is_pinned())
            self._count(func, [("upload", int(not (non_blocking and pinned)))])
        elif to_kind != self.DEVICE:
            self._count(func, [("download", 1)])
        else:
            self._count(func)
        return func(*args, **kwargs)

    # -------------------------------------------------------------- Python-level spellings
    def __enter__(self):
        originals = self._originals

        def host_read(name):
            def counted(tensor, *args, **kwargs):
                if not self._quiet and self._on_device(tensor):
                    self.record(ops=1, waits=1, kind="read")   # a copy to the host
                return originals[name](tensor, *args, **kwargs)
            return counted
        for name in _HOST_READS:
            setattr(torch.Tensor, name, host_read(name))
        if self.device_type is None:               # the CUDA paths: the host is told apart
            # functions (not bound methods), so that the tensor is their first argument
            torch.Tensor.cpu = lambda tensor, *a, **k: self._to_host(tensor, *a, **k)
            torch.Tensor.to = lambda tensor, *a, **k: self._to(tensor, *a, **k)
            torch.Tensor.pin_memory = lambda tensor, *a, **k: self._pin_memory(tensor)
            torch.Tensor.is_pinned = lambda tensor, *args, **kwargs: (
                _storage(tensor) in self._pinned)
            transfer.stages_in_pinned_memory = lambda tensor, device: (
                self._kind(tensor) != self.DEVICE and _storage(tensor) not in self._pinned)
        self.active = True
        return super().__enter__()

    def __exit__(self, *exc):
        for name, original in self._originals.items():
            setattr(torch.Tensor, name, original)
        transfer.stages_in_pinned_memory = self._stages
        self.active = False
        return super().__exit__(*exc)

    def _host_copy(self, tensor: torch.Tensor, pinned: bool = False) -> torch.Tensor:
        with self.uncounted():
            out = tensor.clone()
        self._mark(out, self.HOST)
        if pinned:
            self._pinned.add(_storage(out))
        return out

    def _to_host(self, tensor, *args, **kwargs):
        if self._quiet:
            return self._originals["cpu"](tensor, *args, **kwargs)
        if not self._on_device(tensor):
            self._made_on_host(tensor)
            return tensor
        self.record(ops=1, waits=1, kind="download")
        return self._host_copy(tensor)

    def _to(self, tensor, *args, **kwargs):
        original = self._originals["to"]
        if self._quiet:
            return original(tensor, *args, **kwargs)
        device, _, non_blocking, _ = torch._C._nn._parse_to(*args, **kwargs)
        if device is None:
            return original(tensor, *args, **kwargs)         # a cast where the tensor is
        if _names_the_host(args, kwargs):
            out = original(tensor, *args, **kwargs)
            if not self._on_device(tensor):
                self._made_on_host(tensor)
                return out
            self.record(ops=1, waits=1, kind="download")
            return self._host_copy(out)
        if self._kind(tensor) == self.DEVICE:
            return original(tensor, *args, **kwargs)
        self._made_on_host(tensor)
        pinned = _storage(tensor) in self._pinned
        out = original(tensor, *args, **kwargs)
        with self.uncounted():
            out = out.clone()                       # the upload's result is a device tensor
        self._mark(out, self.DEVICE)
        # blocking, torch waits for the stream after the copy; from pageable memory the
        # copy itself waits
        self.record(ops=1, waits=int(not (non_blocking and pinned)), kind="upload")
        return out

    def _pin_memory(self, tensor, *args, **kwargs):
        if self._on_device(tensor):
            raise RuntimeError("cannot pin a device tensor")
        self._made_on_host(tensor)
        return self._host_copy(tensor, pinned=True)


def force_cuda_paths(trainer, renderer: str = "torch") -> None:
    """The code paths a CUDA run takes, on whatever device ``trainer`` runs; ``renderer``
    ``gsplat``: the render loss through gsplat's rasteriser, whose CUDA kernels the census
    replaces by stand-ins (``gsplat_stand_in``)."""
    trainer.criterion.nn_method = "cdist"
    for group in trainer.optimizer.param_groups:
        group["fused"], group["foreach"] = True, False
    if renderer == "gsplat":
        from ..render.gsplat_backend import render_scenes_gsplat
        trainer.criterion.renderer = render_scenes_gsplat
    elif renderer == "torch":                      # ours, without the reads it makes on CPUs only
        from ..render import render_scenes
        trainer.criterion.renderer = functools.partial(render_scenes, wait_free=True)
    else:
        raise ValueError(f"renderer must be torch or gsplat, got {renderer!r}")


def optimizer_host_tensors(optimizer) -> list[torch.Tensor]:
    """The step counters that a CUDA run keeps on the host (all but fused / capturable AdamW)."""
    keep_on_device = any(g.get("fused") or g.get("capturable") for g in optimizer.param_groups)
    if keep_on_device:
        return []
    return [state["step"] for state in optimizer.state.values() if "step" in state]


def batch_host_tensors(batch: dict) -> list[torch.Tensor]:
    """The tensors of a batch that stay on the host in a CUDA run (``batch.HOST_KEYS``)."""
    return [t for key in HOST_KEYS for t in tensors_in(batch.get(key))]


def census_of_steps(trainer, batches, cuda_paths: bool, renderer: str = "torch",
                    warm_up: bool = True) -> Census:
    """Census of ``trainer.train_step`` over ``batches``, by the phases the step marks
    (``training_phases``). ``warm_up``: the first batch's step
    is a warm-up, not counted (the first step makes the optimizer's state and the device
    constants that later steps reuse). ``renderer`` (with ``cuda_paths``): ``torch`` ours,
    ``gsplat`` gsplat's rasteriser as it runs on CUDA, its kernels replaced by stand-ins that
    count what they launch and read (``gsplat_stand_in``)."""
    if cuda_paths:
        force_cuda_paths(trainer, renderer)
    counted = batches[1:] if warm_up else batches
    host = optimizer_host_tensors(trainer.optimizer) + \
        [t for batch in counted for t in batch_host_tensors(batch)] if cuda_paths else ()
    census = Census(steps=len(counted))
    device_type = None if cuda_paths else trainer.device.type
    mode = CensusMode(census, device_type, host)
    with _gsplat_stand_in(mode, cuda_paths and renderer == "gsplat"):
        if warm_up:
            trainer.train_step(batches[0])
        if counted:
            with mode:
                for batch in counted:
                    trainer.train_step(batch)
    return census


@contextlib.contextmanager
def _gsplat_stand_in(mode: CensusMode, active: bool):
    if not active:
        yield
        return
    from .gsplat_stand_in import gsplat_kernels_counted_by
    with gsplat_kernels_counted_by(mode):
        yield
