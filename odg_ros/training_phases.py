"""The phases of a training step, marked where they run: ``with training_phase("forward"):``
opens a ``torch.profiler.record_function`` range "odg.train.<phase>". A profiler trace shows
them, and the census (``odg profile train``) reads them to count ops and host waits by phase.
A range costs a few microseconds a step; inside a ``torch.compile`` trace it is nothing (the
compiled code has no ranges)."""
from __future__ import annotations

from contextlib import nullcontext

import torch
from torch.profiler import record_function

PREFIX = "odg.train."
# in the order a step runs them; "render" is the render loss, inside "losses"
PHASES = ("data", "forward", "losses", "render", "backward", "optimizer")


def training_phase(name: str):
    """A context manager marking the phase ``name`` (one of PHASES) of a training step."""
    if name not in PHASES:
        raise ValueError(f"unknown training phase {name!r}; one of {', '.join(PHASES)}")
    if torch.compiler.is_compiling():
        return nullcontext()
    return record_function(PREFIX + name)
