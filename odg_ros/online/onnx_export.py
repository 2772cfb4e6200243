"""The node's online step as an ONNX graph with named inputs (``odg export --onnx``).

An ONNX graph has no state: the node's step writes the newest set's features into a ring
it keeps, the exported one takes the history of features as inputs and returns it updated.
Everything is in time order (frame t = the set t history frames back, 0 = the current set):

    images uint8 [N, H, W, 3]; ego2img float32 [k, N, 4, 4]; ego_warp float32 [k, 4, 4];
    time_delta float32 [k]; history_length int64 [1]; replace_newest bool [1];
    img2ego float32 [N, 4, 4]; image_bounds float32 [N, 4]; features_0..features_{L-1}
      -> labels, confidence uint8 [X, Y, Z]; boxes float32 [D, 9], score float32 [D],
         label int64 [D], valid bool [D]; observed uint8 [X, Y, Z];
         features_0_out..features_{L-1}_out (the history's features with the current set's
         first: the next run's features_l)

Shapes, units and frames of each: ``INPUTS`` / ``OUTPUTS`` below and docs/compiled_node.md;
the host side that makes the inputs from CameraInfo, extrinsics, poses and stamps is
online/onnx_inputs.py. ``NamedInputStep`` wraps the node's step unchanged: it shifts the
history by one slot (or not, where the set replaces the newest frame), packs the named
geometry into the step's ``GeometryLayout`` (one concatenation) and runs the step, which
writes slot 0. The history copy replaces the copy the stateless ring needs anyway, so the
graph does the node's work plus one pass over the history memory; no loop, no host read.

The graph is one self-contained file where it fits protobuf's 2 GB; a larger one keeps its
weights in a ``.data`` file beside it, and ``export_onnx`` names every file it wrote.
"""
from __future__ import annotations

import contextlib
import json
import logging
import warnings
from pathlib import Path

import torch
from torch import nn

from ..classes import BOX_CLASSES
from .step import OnlineStep
from ..network.visibility import DEFAULT_MIN_CLEAR

# name -> what it is (the docs' table and the export report say the same)
INPUTS = {
    "images": "uint8 [N, H, W, 3] the current set, RGB, resized and cropped to the network "
              "input (preprocess.resize_crop), cameras in the training rig's order",
    "ego2img": "float32 [k, N, 4, 4] frame t's ego -> its network-input pixels (u*d, v*d, d, 1)",
    "ego_warp": "float32 [k, 4, 4] T_ego(frame t)_from_ego(current): P_t^-1 P_0",
    "time_delta": "float32 [k] seconds from frame t to the current set (>= 0)",
    "history_length": "int64 [1] frames of the inputs in use, 1..k (1 after a history reset)",
    "replace_newest": "bool [1] true: the current set takes the newest history frame's place; "
                      "false: the history moves back one frame",
    "img2ego": "float32 [N, 4, 4] the inverse of ego2img[0] (the visibility's rays)",
    "image_bounds": "float32 [N, 4] (u0, v0, u1, v1) each camera's whole image in "
                    "network-input pixels",
    "features_l": "float32 [k, G, N*(h_l+1), w_l, C/G] FPN level l's features of frames "
                 "0..k-1 (the previous run's features_l_out; zeros at the start)",
}
OUTPUTS = {
    "labels": "uint8 [X, Y, Z] class per voxel (free = the model's class count)",
    "confidence": "uint8 [X, Y, Z] 0..255, the label's score",
    "boxes": "float32 [D, 9] (cx, cy, cz, w, l, h, yaw, vx, vy) in the current ego frame",
    "score": "float32 [D] box scores, descending among the valid ones",
    "label": "int64 [D] box classes",
    "valid": "bool [D] the box passes the score threshold (valid ones first)",
    "observed": "uint8 [X, Y, Z] 1: a camera sees the voxel; 0: unknown",
    "features_l_out": "features_l with the current set as frame 0: the next run's features_l",
}
GRID_OUTPUTS = ("labels", "confidence", "boxes", "score", "label", "valid", "observed")


def feature_names(levels: int, suffix: str = "") -> list[str]:
    return [f"features_{level}{suffix}" for level in range(levels)]


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


class NamedInputStep(nn.Module):
    """``OnlineStep`` (unchanged) over named inputs in time order, with its feature ring as
    an input and an output (``features_l``, slot t = frame t) instead of state."""

    def __init__(self, step: OnlineStep):
        super().__init__()
        self.step = step
        layout = step.layout
        k, N = layout.capacity, layout.num_cams
        # the step's packed geometry from the named inputs, in the layout's own order: a
        # field the layout gains fails here, at export, not as a silently shifted buffer
        self.packing = {"ego2img": k * N * 16, "ego_warp": k * 16, "time_delta": k,
                        "frame_index": layout.num_frames, "slot": 1, "img2ego": N * 16,
                        "bounds": N * 4}
        sizes = {name: s.stop - s.start for name, s in layout.slices.items()}
        if sizes != self.packing or list(sizes) != list(self.packing):
            raise RuntimeError(f"the step's geometry layout {sizes} is not the one the ONNX "
                               f"export packs {self.packing}: update NamedInputStep")
        self.register_buffer("frames", torch.arange(k), persistent=False)
        self.register_buffer("steps", torch.arange(layout.num_frames), persistent=False)
        self.register_buffer("slot", torch.zeros(1), persistent=False)

    def forward(self, images, ego2img, ego_warp, time_delta, history_length, replace_newest,
                img2ego, image_bounds, *history):
        k = self.step.layout.capacity
        # frame t's features move to slot t + 1 (the oldest drops out), or stay where the
        # current set replaces the newest frame; the step then writes slot 0
        source = (self.frames - (~replace_newest).long()).clamp(min=0)
        memory = [h.index_select(0, source) for h in history]
        self.step.ring.use_memory([m.flatten(0, 1) for m in memory])    # views: written in place
        # time step t reads frame t, or the oldest in use where the history is shorter
        frame_index = torch.minimum(self.steps, history_length.clamp(1, k) - 1)
        parts = {"ego2img": ego2img, "ego_warp": ego_warp, "time_delta": time_delta,
                 "frame_index": frame_index, "slot": self.slot, "img2ego": img2ego,
                 "bounds": image_bounds}
        packed = torch.cat([parts[name].reshape(-1).float() for name in self.packing])
        labels, confidence, boxes, score, label, valid, observed = self.step(images, packed)
        grid = tuple(self.step.cfg.grid_shape)
        return (labels.view(grid), confidence.view(grid), boxes, score, label, valid,
                observed.view(grid), *memory)


def example_inputs(step: OnlineStep, seed: int = 0) -> dict[str, torch.Tensor]:
    """Named inputs of finite values: random images and history, the identity geometry of
    a full history (only their shapes and dtypes are traced)."""
    cfg, layout = step.cfg, step.layout
    k, N = layout.capacity, layout.num_cams
    generator = torch.Generator().manual_seed(seed)
    H, W = cfg.image_size
    inputs = {
        "images": torch.randint(0, 256, (N, H, W, 3), dtype=torch.uint8, generator=generator),
        "ego2img": torch.eye(4).expand(k, N, 4, 4).contiguous(),
        "ego_warp": torch.eye(4).expand(k, 4, 4).contiguous(),
        "time_delta": torch.zeros(k),
        "history_length": torch.full((1,), k, dtype=torch.long),
        "replace_newest": torch.zeros(1, dtype=torch.bool),
        "img2ego": torch.eye(4).expand(N, 4, 4).contiguous(),
        "image_bounds": torch.tensor([0.0, 0.0, W, H]).expand(N, 4).contiguous(),
    }
    for name, m in zip(feature_names(len(step.ring.memory)), step.ring.memory):
        inputs[name] = torch.randn(k, m.shape[0] // k, *m.shape[1:],
                                   generator=generator).to(m.dtype)
    return inputs


# protobuf's limit on one message; the graph stays one file below it (with room to spare)
SINGLE_FILE_LIMIT = 2 ** 31 - 2 ** 26


def export_onnx(model: nn.Module, cfg, path, capacity: int | None = None, opset: int = 20,
                min_clear: float = DEFAULT_MIN_CLEAR):
    """Write the online step over a history of ``capacity`` frames (default: the model's)
    to ``path`` -> the NamedInputStep exported, its example inputs by name, and every file
    written [(path, bytes)]: ``path`` alone when the graph fits one file, else ``path`` and
    its external weights. ``min_clear``: the visibility's, as the node's
    ``visibility_min_clear``."""
    from torch.nn.attention import SDPBackend, sdpa_kernel
    k = cfg.num_frames if capacity is None else int(capacity)
    step = OnlineStep(model.eval(), cfg, k, "cpu", min_clear=min_clear).eval()
    named = NamedInputStep(step).eval()
    inputs = example_inputs(step)
    levels = len(step.ring.memory)
    outputs = list(GRID_OUTPUTS) + feature_names(levels, "_out")
    # the math attention traces to plain ops: the CPU flash kernel's decomposition gives
    # strides its reshape cannot view
    with torch.no_grad(), sdpa_kernel(SDPBackend.MATH), _quiet_export():
        torch.onnx.export(named, tuple(inputs.values()), str(path), dynamo=True,
                          opset_version=opset, input_names=list(inputs),
                          output_names=outputs,
                          custom_translation_table={torch.ops.aten.sort.stable: _sort_stable,
                                                    torch.ops.aten.searchsorted.Tensor:
                                                        _searchsorted},
                          verbose=False, external_data=True)
    files = _single_file_if_it_fits(Path(path), metadata(cfg, k, min_clear))
    return named, inputs, files


def metadata(cfg, capacity: int, min_clear: float = DEFAULT_MIN_CLEAR) -> dict[str, str]:
    """What a deployment needs to read the outputs, stored in the file (onnxruntime:
    ``session.get_modelmeta().custom_metadata_map``)."""
    from ..classes import occ_labels
    return {"odg.model": cfg.name, "odg.grid_shape": json.dumps(list(cfg.grid_shape)),
            "odg.pc_range": json.dumps(list(cfg.pc_range)),
            "odg.voxel_size": json.dumps(cfg.voxel_size),
            "odg.free_label": json.dumps(cfg.num_classes),
            "odg.classes": json.dumps(list(occ_labels(cfg.dataset).names)),
            "odg.box_classes": json.dumps(list(BOX_CLASSES[:cfg.num_box_classes])),
            "odg.image_size": json.dumps(list(cfg.image_size)),
            "odg.history_frames": json.dumps(capacity),
            "odg.visibility_min_clear": json.dumps(min_clear),
            "odg.calibrated": json.dumps(cfg.calibration is not None),
            "odg.inputs": "docs/compiled_node.md, ONNX export"}


def graph_signature(path) -> dict[str, dict[str, str]]:
    """The graph's inputs and outputs as written: {"inputs": {name: "uint8 [6, 64, 176, 3]"},
    "outputs": {...}} (the weights are not read)."""
    import onnx
    graph = onnx.load(str(path), load_external_data=False).graph

    def described(value) -> str:
        tensor = value.type.tensor_type
        dtype = onnx.helper.tensor_dtype_to_np_dtype(tensor.elem_type)
        return f"{dtype} {[d.dim_value for d in tensor.shape.dim]}"
    return {"inputs": {v.name: described(v) for v in graph.input},
            "outputs": {v.name: described(v) for v in graph.output}}

# Messages of torch.onnx and onnxscript that say nothing a user can act on: the exporter
# registers torchvision's operators where torchvision is installed (this graph has none),
# and the optimiser leaves the LayerNormalizations of constants unfolded (the first decoder
# layer's encodings of the learned initial queries; onnxruntime folds them at load).
_NOISE = {"torch.onnx._internal.exporter._registration": ("torchvision is not installed",),
          "onnxscript.optimizer._constant_folding": ("Skipping constant folding for op",)}


class _DropMessages(logging.Filter):
    def __init__(self, prefixes):
        super().__init__()
        self.prefixes = prefixes

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(self.prefixes)


@contextlib.contextmanager
def _quiet_export():
    """The export without the messages of ``_NOISE`` and torch's deprecation notice about
    its own pytree internals (raised inside torch.export); every other warning passes."""
    filters = [(logging.getLogger(name), _DropMessages(prefixes))
               for name, prefixes in _NOISE.items()]
    for logger, f in filters:
        logger.addFilter(f)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)`",
                                    category=FutureWarning)
            yield
    finally:
        for logger, f in filters:
            logger.removeFilter(f)


def _single_file_if_it_fits(path: Path, metadata: dict[str, str] | None = None
                            ) -> list[tuple[Path, int]]:
    """The exporter writes the weights beside the graph (``path.data``); folded back into
    ``path`` where the whole stays under SINGLE_FILE_LIMIT (a graph copied without its
    ``.data`` file would not load); ``metadata`` added to the graph's properties.
    -> every file of the export with its size."""
    import onnx
    data = [p for p in path.parent.glob(path.name + "*") if p != path]
    total = path.stat().st_size + sum(p.stat().st_size for p in data)
    fold = bool(data) and total < SINGLE_FILE_LIMIT
    if fold or metadata:
        graph = onnx.load(str(path), load_external_data=fold)
        for key, value in (metadata or {}).items():
            graph.metadata_props.add(key=key, value=value)
        onnx.save_model(graph, str(path), save_as_external_data=False)
    if fold:
        for p in data:
            p.unlink()
        data = []
    return [(p, p.stat().st_size) for p in [path, *data]]
