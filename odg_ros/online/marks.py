"""Named time ranges on the online step: where ``odg bench`` reads its per-stage and
per-layer times, on the very step the node runs.

``mark(name)`` wraps a stage of ``OnlineStep`` (step.py). It costs about 2 microseconds and
records nothing, unless
- a ``MarkRecorder`` is recording (``with recorder:``; odg bench): wall time per range on the
  CPU, CUDA events on a GPU (read after the step: no host wait inside it);
- a profiler is on (``torch.profiler``): a ``record_function`` range "odg.<name>", seen in
  its traces.
Inside a ``torch.compile`` trace a mark is nothing (the compiled code has no ranges; Dynamo
would drop a ``record_function`` with a warning), and a CUDA graph replays none. So stages are
timed on eager steps; a compiled or graph-replayed step is timed whole.

``DecoderMarks`` ranges every decoder layer (``layer1``..), each part of a layer
(``layer1.sampling``..) and under a query budget the skip layer and the keep-scores, by forward
hooks installed for the duration of a ``with`` (an eager step only: hooks added to a compiled
module would make it compile again).
"""
from __future__ import annotations

import statistics
import time
from contextlib import contextmanager, nullcontext

import torch
from torch.profiler import record_function

PREFIX = "odg."
# OnlineStep's stages in execution order (``padding`` where the model pads its grid,
# ``calibration`` where its checkpoint is calibrated, ``visibility`` where the step computes it)
STEP_STAGES = ("backbone", "decoder", "grid", "padding", "calibration", "boxes", "visibility")
# the parts of a decoder layer, in execution order (attributes of decoder.DecoderLayer)
LAYER_PARTS = ("position", "box_position", "attention", "sampling", "mixing", "ffn", "points",
               "boxes")

_NOTHING = nullcontext()
_recorder: MarkRecorder | None = None


def mark(name: str):
    """A context manager that times ``name`` where something records (module docstring)."""
    if torch.compiler.is_compiling():
        return _NOTHING
    if _recorder is not None:
        return _recorder.range(name)
    if torch.autograd._profiler_enabled():
        return record_function(PREFIX + name)
    return _NOTHING


class MarkRecorder:
    """Milliseconds per mark over the steps run inside ``with recorder:`` (one recorder at a
    time); on CUDA from events, resolved by ``flush`` (called by ``times``). On the CPU by
    ``clock`` (seconds): wall time by default (``time.perf_counter``), or CPU time
    (``time.process_time``: the process's, torch's threads included; ``time.thread_time``:
    the calling thread's)."""

    def __init__(self, device, clock=time.perf_counter):
        self.cuda = torch.device(device).type == "cuda"
        self.clock = clock
        self.times: dict[str, list[float]] = {}
        self._open, self._pending = {}, []

    def __enter__(self):
        global _recorder
        if _recorder is not None:
            raise RuntimeError("another MarkRecorder is recording")
        _recorder = self
        return self

    def __exit__(self, *exc):
        global _recorder
        _recorder = None

    def start(self, name: str) -> None:
        if self.cuda:
            event = torch.cuda.Event(enable_timing=True)
            event.record()
            self._open[name] = event
        else:
            self._open[name] = self.clock()

    def stop(self, name: str) -> None:
        begin = self._open.pop(name)
        if self.cuda:
            end = torch.cuda.Event(enable_timing=True)
            end.record()
            self._pending.append((name, begin, end))
        else:
            self.times.setdefault(name, []).append((self.clock() - begin) * 1e3)

    @contextmanager
    def range(self, name: str):
        self.start(name)
        yield
        self.stop(name)

    def flush(self) -> dict[str, list[float]]:
        if self._pending:
            torch.cuda.synchronize()
            for name, begin, end in self._pending:
                self.times.setdefault(name, []).append(begin.elapsed_time(end))
            self._pending.clear()
        return self.times

    def medians(self) -> dict[str, float]:
        return {name: statistics.median(v) for name, v in self.flush().items()}


class DecoderMarks:
    """``with DecoderMarks(decoder, recorder):`` ranges for every layer of ``decoder`` and its
    parts, the skip layer and the keep-scores (module docstring)."""

    def __init__(self, decoder: torch.nn.Module, recorder: MarkRecorder):
        self.decoder, self.recorder, self.handles = decoder, recorder, []

    def _hook(self, module, name):
        def pre(*_):
            self.recorder.start(name)

        def post(*_):
            self.recorder.stop(name)
        self.handles += [module.register_forward_pre_hook(pre), module.register_forward_hook(post)]

    def _hook_parts(self, layer, name):
        self._hook(layer, name)
        for part in LAYER_PARTS:
            if getattr(layer, part, None) is not None:
                self._hook(getattr(layer, part), f"{name}.{part}")

    def __enter__(self):
        for index, layer in enumerate(self.decoder.layers):
            self._hook_parts(layer, f"layer{index + 1}")
        heads = self.decoder.budget_heads
        self._hook_parts(heads.skip_layer, "skip_layer")
        self._hook(heads.static_score, "keep_static")
        self._hook(heads.dynamic_score, "keep_dynamic")
        return self

    def __exit__(self, *exc):
        for handle in self.handles:
            handle.remove()
        self.handles.clear()
