"""The online step (``OnlineStep``) over a full ring as an ONNX graph (``odg export --onnx``).

The node's step writes the newest frame into its ring in place; an ONNX graph has no state,
so the exported function takes the ring as inputs and returns it updated:

    images uint8 [N, H, W, 3], packed float32 [n], ring_0..ring_{L-1}
      -> labels, confidence uint8 [X*Y*Z], boxes [D, 9], score [D], label [D], valid [D],
         observed uint8 [X*Y*Z] (a camera sees the voxel),
         ring_0_out..ring_{L-1}_out (the ring with the newest frame written)

``packed`` is the geometry buffer the node fills (``GeometryLayout``); a runtime feeds the
returned ring to the next step. Shapes are static, as in the node (every ring slot read).

The graph is one self-contained file where it fits protobuf's 2 GB; a larger one keeps its
weights in a ``.data`` file beside it, and ``export_onnx`` names every file it wrote.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from .step import OnlineStep

OUTPUT_NAMES = ("labels", "confidence", "boxes", "score", "label", "valid", "observed")


def _sort_stable(self, stable=None, dim: int = -1, descending: bool = False):
    """aten.sort.stable as ONNX TopK over the whole axis: TopK breaks ties by the lower
    index first, which is a stable sort (the post-processing's voxel grouping relies on it)."""
    from onnxscript import opset18 as op
    size = op.Reshape(op.Gather(op.Shape(self), dim, axis=0), op.Constant(value_ints=[1]))
    return op.TopK(self, size, axis=dim, largest=descending, sorted=True)


def _searchsorted(sorted_sequence, self, out_int32: bool = False, right: bool = False,
                  side=None, sorter=None):
    """aten.searchsorted (left side) as ONNX: per row, the number of entries below the value
    (the visibility's sequences are short, ~170 samples)."""
    from onnxscript import opset18 as op
    below = op.Cast(op.Less(sorted_sequence, self), to=7)          # int64
    return op.ReduceSum(below, op.Constant(value_ints=[-1]), keepdims=1)


class StatelessStep(nn.Module):
    """``OnlineStep`` with its ring memory as inputs and outputs instead of state."""

    def __init__(self, step: OnlineStep):
        super().__init__()
        self.step = step

    def forward(self, images: torch.Tensor, packed: torch.Tensor, *ring: torch.Tensor):
        memory = [m.clone() for m in ring]       # written in place by the step
        self.step.ring._memory = memory
        return (*self.step(images, packed), *memory)


def example_inputs(step: OnlineStep, seed: int = 0):
    """Random images and a full ring of random features (only their shapes are traced)."""
    cfg = step.cfg
    generator = torch.Generator().manual_seed(seed)
    H, W = cfg.image_size
    images = torch.randint(0, 256, (cfg.num_cams, H, W, 3), dtype=torch.uint8,
                           generator=generator)
    ring = [torch.randn(m.shape, generator=generator).to(m.dtype) for m in step.ring._memory]
    return images, ring


# protobuf's limit on one message; the graph stays one file below it (with room to spare)
SINGLE_FILE_LIMIT = 2 ** 31 - 2 ** 26


def export_onnx(model: nn.Module, cfg, path, capacity: int | None = None, opset: int = 20):
    """Write the online step over a ring of ``capacity`` (default: the model's frames) to
    ``path`` -> the StatelessStep exported, the example inputs traced, and every file
    written [(path, bytes)]: ``path`` alone when the graph fits one file, else ``path`` and
    its external weights."""
    from torch.nn.attention import SDPBackend, sdpa_kernel
    k = cfg.num_frames if capacity is None else int(capacity)
    step = OnlineStep(model.eval(), cfg, k, "cpu").eval()
    stateless = StatelessStep(step).eval()
    images, ring = example_inputs(step)
    packed = torch.zeros(step.layout.size)     # the node's warm-up geometry: finite
    step.layout.pack(packed.numpy(), 0.0, np.broadcast_to(np.eye(4), (k, 4, 4)), 0.0, 0, 0)
    names = ["images", "packed"] + [f"ring_{i}" for i in range(len(ring))]
    outputs = list(OUTPUT_NAMES) + [f"ring_{i}_out" for i in range(len(ring))]
    # the math attention traces to plain ops: the CPU flash kernel's decomposition gives
    # strides its reshape cannot view
    with torch.no_grad(), sdpa_kernel(SDPBackend.MATH):
        torch.onnx.export(stateless, (images, packed, *ring), str(path), dynamo=True,
                          opset_version=opset, input_names=names, output_names=outputs,
                          custom_translation_table={torch.ops.aten.sort.stable: _sort_stable,
                                                    torch.ops.aten.searchsorted.Tensor:
                                                        _searchsorted},
                          verbose=False, external_data=True)
    return stateless, (images, packed, *ring), _single_file_if_it_fits(Path(path))


def _single_file_if_it_fits(path: Path) -> list[tuple[Path, int]]:
    """The exporter writes the weights beside the graph (``path.data``); folded back into
    ``path`` where the whole stays under SINGLE_FILE_LIMIT (a graph copied without its
    ``.data`` file would not load). -> every file of the export with its size."""
    import onnx
    data = [p for p in path.parent.glob(path.name + "*") if p != path]
    total = path.stat().st_size + sum(p.stat().st_size for p in data)
    if data and total < SINGLE_FILE_LIMIT:
        graph = onnx.load(str(path), load_external_data=True)
        onnx.save_model(graph, str(path), save_as_external_data=False)
        for p in data:
            p.unlink()
        data = []
    return [(p, p.stat().st_size) for p in [path, *data]]
