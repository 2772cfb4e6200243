"""How the online step runs: the execution mode (eager, compiled, CUDA graphs, or a compiled
step file of ``odg export --aoti``), the graph capture, and the query budgets a predictor
runs (one static-shape step each)."""
from __future__ import annotations

import torch

from ..network.budget import QueryBudget, budget_ladder, budget_of
from .budget_policy import BudgetPolicy
from .step import MODES

# compile="auto": graphs on CUDA; on the CPU the mode measured fastest for odg_cpu
# (docs/compiled_node.md)
CPU_DEFAULT_MODE = "eager"


def resolve_mode(mode: str, device, compiled_step: bool = False) -> str:
    """compile parameter -> eager | compiled | graphs ("auto": graphs on CUDA; with a
    compiled step file, compiled on the CPU: that file is what runs)."""
    device = torch.device(device)
    if mode == "auto":
        if device.type == "cuda":
            return "graphs"
        return "compiled" if compiled_step else CPU_DEFAULT_MODE
    if mode not in MODES:
        raise ValueError(f"compile {mode!r}: expected auto or one of {MODES}")
    if mode == "eager" and compiled_step:
        raise ValueError("compile eager runs no compiled step: leave compiled_step empty, "
                         "or use compile auto, compiled or graphs")
    if mode == "graphs" and device.type != "cuda":
        raise ValueError("compile=graphs replays CUDA graphs: it needs a CUDA device "
                         "(use compiled or eager on the CPU)")
    return mode


class CudaGraphStep:
    """The step captured once into a CUDA graph, after two runs on a side stream (cuBLAS and
    the allocator settle there). The graph reads the static input buffers it was captured
    with, and ``replay()`` returns the output tensors of the capture, rewritten: a result
    must be copied out before the next replay."""

    def __init__(self, function, images: torch.Tensor, packed: torch.Tensor, device):
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(2):
                function(images, packed)
        torch.cuda.current_stream(device).wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.outputs = function(images, packed)

    def replay(self):
        self.graph.replay()
        return self.outputs


def resolve_budget(query_budget, model, cfg):
    """query_budget "full" | "auto" | a fraction in (0, 1] | one ``QueryBudget`` (a rung of
    the ladder, bench/budget_cost.py) -> (the budgets the step runs, None standing for the
    full one; the ``BudgetPolicy`` of "auto" or None)."""
    if query_budget in ("full", None):
        return [None], None
    heads = model.decoder.budget_heads
    if isinstance(query_budget, QueryBudget):
        ladder, policy = [query_budget], None
    elif query_budget == "auto":
        ladder = budget_ladder(cfg)
        policy = BudgetPolicy(ladder)
    else:
        try:
            fraction = float(query_budget)
        except (TypeError, ValueError):
            raise ValueError(f"query_budget {query_budget!r}: expected full, auto or a "
                             "fraction in (0, 1]") from None
        if fraction == 1.0:
            return [None], None
        ladder, policy = [budget_of(cfg, fraction)], None
    if not heads.is_trained:
        raise ValueError(f"query_budget {query_budget}: this checkpoint's keep-score and skip "
                         "heads are not trained; use query_budget full")
    return ladder, policy


def load_compiled_step(path, step, model, precision: str, visibility: bool, min_clear: float,
                       for_cuda_graph: bool):
    """The .pt2 step of ``odg export --aoti`` (artifact.py), checked against ``step`` (an
    OnlineStep over ``model``) -> f(images, packed) on ``step``'s feature ring, whose memory it
    reads and writes in place. A file built for another model, configuration, precision,
    history length, device or torch is refused (StaleArtifact)."""
    from .artifact import load_artifact, step_signature
    compiled = load_artifact(path, step_signature(model, step.cfg, step.layout.capacity,
                                                  step.device, precision, visibility,
                                                  min_clear),
                             for_cuda_graph=for_cuda_graph)
    ring = step.ring

    def run(images, packed):
        return compiled(images, packed, *ring.memory)
    return run
