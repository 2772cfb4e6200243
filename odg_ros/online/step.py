"""The online step as one function of static-shape device tensors (the node's compiled step).

    images uint8 [N, H, W, 3] + packed geometry float32 [n]
      -> normalise -> backbone -> ring slot write -> decoder over all k ring slots
      -> grid (voxelise, padding) + top-D boxes with a valid mask + the voxels the cameras
         observe (visibility.py)

Every step has the same shapes and no host read, whatever the history's fill level: the
decoder samples all ``capacity`` ring slots and a frame index (in the packed geometry) says
which slot each of the model's time steps reads (a missing frame repeats the oldest); the
geometry of an empty slot is the oldest frame's, so it stays finite. So one trace serves
every step (``torch.compile(fullgraph=True)``) and the step can be replayed as a CUDA graph.

Execution modes (``OnlinePredictor(compile=...)``):
- eager: the step as plain PyTorch;
- compiled: ``torch.compile(fullgraph=True, dynamic=False)`` (Inductor);
- graphs: compiled, then captured once into a CUDA graph after a warm-up and replayed
  (CUDA only): one launch per step instead of thousands of kernel launches.
"""
from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn

from ..model_config import ModelConfig
from ..network.backbone import folded_for_inference
from ..network.budget import QueryBudget, needed_queries
from ..network.calibration import Calibration
from ..network import int8_encoder
from ..network.feature_ring import FeatureRing
from ..network.padding import OccupancyPadding
from ..network.postprocess import ranked_boxes, stray_voxels, voxelise
from ..network.precision import (decoder_half_dtype, half_dtype, precision_context,
                                 with_half_matrix_weights)
from ..preprocess import IMAGENET_MEAN, IMAGENET_STD
from .marks import mark
from ..network.visibility import DEFAULT_MIN_CLEAR, Visibility

MODES = ("eager", "compiled", "graphs")


class GeometryLayout:
    """Offsets of the packed per-step geometry (one host-to-device copy per step):
    ego2img [1, k, N, 4, 4], ego_warp [1, k, 4, 4], time_delta [1, k] in storage-slot order,
    frame_index [num_frames] (slot read by each time step), slot [1] (the slot written);
    for the visibility of the current set: img2ego [N, 4, 4] (its ego2img inverted) and
    bounds [N, 4] (u0, v0, u1, v1: each camera's whole image in network-input pixels)."""

    def __init__(self, capacity: int, num_cams: int, num_frames: int):
        self.capacity, self.num_cams, self.num_frames = capacity, num_cams, num_frames
        sizes = {"ego2img": capacity * num_cams * 16, "ego_warp": capacity * 16,
                 "time_delta": capacity, "frame_index": num_frames, "slot": 1,
                 "img2ego": num_cams * 16, "bounds": num_cams * 4}
        self.slices, start = {}, 0
        for name, size in sizes.items():
            self.slices[name] = slice(start, start + size)
            start += size
        self.size = start

    def pack(self, out: np.ndarray, ego2img, ego_warp, time_delta, frame_index, slot,
             img2ego=np.eye(4), bounds=(0.0, 0.0, 1.0, 1.0)) -> None:
        """Host arrays in storage-slot order -> ``out`` float32 [size] (indices are exact)."""
        out[self.slices["ego2img"]] = np.asarray(ego2img).ravel()
        out[self.slices["ego_warp"]] = np.asarray(ego_warp).ravel()
        out[self.slices["time_delta"]] = np.asarray(time_delta).ravel()
        out[self.slices["frame_index"]] = frame_index
        out[self.slices["slot"]] = slot
        N = self.num_cams
        out[self.slices["img2ego"]] = np.broadcast_to(img2ego, (N, 4, 4)).ravel()
        out[self.slices["bounds"]] = np.broadcast_to(bounds, (N, 4)).ravel()

    def unpack(self, packed: torch.Tensor):
        k, N = self.capacity, self.num_cams
        part = {name: packed[s] for name, s in self.slices.items()}
        return (part["ego2img"].view(1, k, N, 4, 4), part["ego_warp"].view(1, k, 4, 4),
                part["time_delta"].view(1, k), part["frame_index"].long(), part["slot"].long())

    def current_view(self, packed: torch.Tensor):
        """(ego2img, img2ego [N, 4, 4], bounds [N, 4]) of the set written this step."""
        N = self.num_cams
        ego2img, _, _, _, slot = self.unpack(packed)
        return (ego2img[0].index_select(0, slot)[0], packed[self.slices["img2ego"]].view(N, 4, 4),
                packed[self.slices["bounds"]].view(N, 4))


class OnlineStep(nn.Module):
    """One online step over device tensors; holds the feature ring (written in place).
    visibility: compute which voxels the cameras observe (network/visibility.py); without it
    the ``observed`` output is empty; min_clear: its least probability of a clear ray. The
    confidence and box scores are the checkpoint's calibrated probabilities where it has a
    calibration (network/calibration.py)."""

    def __init__(self, model: nn.Module, cfg: ModelConfig, capacity: int, device,
                 precision: str = "fp32", visibility: bool = True,
                 min_clear: float = DEFAULT_MIN_CLEAR):
        super().__init__()
        self.model, self.cfg, self.precision = model, cfg, precision
        self.free_label = cfg.num_classes           # Occ3D: free = the class count
        self.device = torch.device(device)
        self.calibration = Calibration(cfg, device)
        self.visibility = Visibility(cfg.grid_shape, cfg.pc_range, cfg.voxel_size,
                                     self.free_label, min_clear, device=device) \
            if visibility else None
        self.layout = GeometryLayout(capacity, cfg.num_cams, cfg.num_frames)
        self.padding = OccupancyPadding(cfg.grid_shape, self.free_label, cfg.score_threshold,
                                        device) if cfg.occupancy_padding else None
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN, device=device),
                             persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD, device=device),
                             persistent=False)
        # backbone and FPN channels-last end to end, as the images come (NHWC): weights in
        # that layout too, or each convolution would re-lay them out inside its kernel
        self.backbone = folded_for_inference(model.backbone)
        self.neck = copy.deepcopy(model.neck).to(memory_format=torch.channels_last)
        self.half = half_dtype(precision)
        if self.half is not None:
            # weights stored in the compute dtype: autocast would cast every weight again at
            # every step (one kernel each); the geometry stays float32 (sampling.full_precision)
            self.backbone = self.backbone.to(self.half)
            self.neck = with_half_matrix_weights(self.neck, self.half)
        self.int8_encoder = None
        if precision == "int8-encoder":
            # static int8 (network/int8_encoder.py): the activation ranges from the side file
            # of these weights, the weight scales from the weights
            fingerprint = int8_encoder.encoder_fingerprint(model.backbone, model.neck)
            ranges = int8_encoder.load_ranges(int8_encoder.ranges_path(fingerprint),
                                              fingerprint)
            H, W = cfg.image_size
            self.int8_encoder = int8_encoder.quantized_encoder(
                self.backbone, self.neck, ranges, torch.zeros(cfg.num_cams, 3, H, W,
                                                             device=self.device))
        decoder_half = decoder_half_dtype(precision)
        if decoder_half is not None:
            self.model = copy.copy(model)                # shares all but the decoder
            self.model._modules = dict(model._modules)
            self.model.decoder = with_half_matrix_weights(model.decoder, decoder_half)
        self.ring = FeatureRing(capacity, cfg.num_groups)
        # CPU, eager (the predictor sets it): the encoder on torch's threads, the rest of the
        # step on one. The decoder's and the grid's kernels are small: on a shared CPU their
        # threads' wake-ups cost more than the threads give (docs/node.md, Speed)
        self.parallel_encoder_only = False
        with torch.no_grad():                                               # shapes only
            H, W = cfg.image_size
            self.ring.check(self.features(torch.zeros(cfg.num_cams, 3, H, W,
                                                      device=self.device)))

    def features(self, images: torch.Tensor) -> list[torch.Tensor]:
        """images [N, 3, H, W] normalised float32 -> L levels [1, N, C, h, w]:
        ``ODG.extract_features`` with the folded channels-last backbone (in bf16 / fp16
        weights and activations where the precision asks for it)."""
        x = images.contiguous(memory_format=torch.channels_last)
        if self.int8_encoder is not None:
            return [f.unsqueeze(0) for f in self.int8_encoder(x)]
        if self.half is not None:
            x = x.to(self.half)
        return [f.unsqueeze(0) for f in self.neck(self.backbone(x))]

    def forward(self, images: torch.Tensor, packed: torch.Tensor,
                budget: QueryBudget | None = None):
        """images uint8 [N, H, W, 3]; packed float32 [layout.size] -> labels, confidence
        uint8 [X*Y*Z]; boxes [D, 9], score [D], label [D], valid [D] (by score); observed
        uint8 [X*Y*Z] (1: a camera sees the voxel; [0] without visibility); with a query
        ``budget`` (network/budget.py) also the queries its keep-scores call needed [2]
        (static, dynamic), from which the host picks the next step's budget."""
        # a traced or compiled step never changes threads (nor reads them)
        split = self.parallel_encoder_only and not torch.compiler.is_compiling() and \
            not torch.jit.is_tracing() and torch.get_num_threads() > 1
        if not split:
            return self._step(images, packed, budget)
        threads = torch.get_num_threads()
        try:
            return self._step(images, packed, budget, one_thread_after_encoder=True)
        finally:
            torch.set_num_threads(threads)

    def _step(self, images: torch.Tensor, packed: torch.Tensor, budget: QueryBudget | None,
              one_thread_after_encoder: bool = False):
        ego2img, ego_warp, time_delta, frame_index, slot = self.layout.unpack(packed)
        with mark("backbone"):          # marks.py: the stage times of odg bench
            x = ((images.float() / 255.0 - self.mean) / self.std).movedim(-1, -3)
            self.ring.write_slot(self.features(x), slot)
        if one_thread_after_encoder:
            torch.set_num_threads(1)
        with precision_context(self.precision, self.device), mark("decoder"):
            output = self.model.decode_stored(self.ring.all_levels(), ego2img, ego_warp,
                                              time_delta, frame_index, False, budget=budget)
        results = self._results(output, packed)
        if budget is None:
            return results
        heads = self.model.decoder.budget_heads
        return (*results, needed_queries(output.keep_scores, output.num_dynamic,
                                         heads.threshold)[0])

    def _results(self, output, packed):
        """The grid and the ranked boxes of ``output`` (see ``forward``)."""
        layer = output.last
        with mark("grid"):
            labels, confidence = voxelise(layer.means, layer.logits, self.cfg, self.free_label)
        if self.padding is not None:        # static shapes too: filters over the whole grid
            grid = (1, *self.cfg.grid_shape)
            with mark("padding"):
                labels, confidence = (t.flatten(1) for t in self.padding(labels.view(grid),
                                                                         confidence.view(grid)))
        labels, confidence = labels[0], confidence[0]
        hazard = None
        if self.calibration.calibrated:
            with mark("calibration"):
                confidence, hazard = self.calibration(labels, confidence,
                                                      hazard=self.visibility is not None)
        if layer.boxes is None:                        # a model without dynamic queries
            empty = layer.means.new_zeros(1, 0)
            boxes, score = layer.means.new_zeros(1, 0, 9), empty
            label, valid = empty.long(), empty.bool()
        else:
            with mark("boxes"):
                boxes, score, label, valid = ranked_boxes(layer.boxes, layer.box_logits,
                                                          self.cfg.box_score_threshold)
                score = self.calibration.box_score(score)
        if self.visibility is None:
            observed = labels.new_zeros(0)
        else:
            with mark("visibility"):
                stray = stray_voxels(layer.means, layer.logits, self.cfg)[0]
                observed = self.visibility(labels, *self.layout.current_view(packed),
                                           hazard=hazard, stray=stray)
        return labels, confidence, boxes[0], score[0], label[0], valid[0], observed


class NodeInferenceModel(nn.Module):
    """The offline model's call (every frame of a sample through the backbone, then the
    decoder) computed with an ``OnlineStep``'s own modules and precision: the folded
    channels-last backbone, bf16 / fp16 weights where ``precision`` asks, float32 feature
    layout, autocast decoder. What ``odg eval --precision`` scores: the node's arithmetic
    on the evaluation's samples."""

    def __init__(self, model: nn.Module, cfg: ModelConfig, device, precision: str):
        super().__init__()
        self.step = OnlineStep(model, cfg, cfg.num_frames, device, precision, visibility=False)
        self.decoder = self.step.model.decoder          # as the model's (budget needs)

    def forward(self, images: torch.Tensor, ego2img: torch.Tensor, ego_warp: torch.Tensor,
                time_delta: torch.Tensor, **decode_options):
        """images [B, T, N, 3, H, W] normalised; geometry as ``ODG.forward``."""
        B, T, N = images.shape[:3]
        levels = self.step.features(images.flatten(0, 2))            # [1, B*T*N, C, h, w]
        levels = [f[0].unflatten(0, (B, T, N)) for f in levels]
        frame_feats = [[f[:, t] for f in levels] for t in range(T)]
        with precision_context(self.step.precision, self.step.device):
            return self.step.model.decode(frame_feats, ego2img, ego_warp, time_delta,
                                          **decode_options)
