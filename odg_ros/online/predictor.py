"""Streaming inference: one camera set in, one occupancy grid + box list out.

The backbone runs on the newest set only; its features are written once into a FeatureRing
(already in the sampling layout) and the rolling history (history.py) keeps each set's pose,
ego->image matrices and stamp. The decoder looks at the cached features of the last k sets,
with the ego motion between them (ego_warp = P_t^-1 P_0) and their time differences. This
gives the same result as running the model offline over the same k sets
(test_online_predictor.py), at the cost of one backbone pass per set instead of k.

The device work of a step is one static-shape function (step.OnlineStep), run eagerly,
compiled, or replayed as a CUDA graph (``compile``, execution.py); the host packs the geometry into one
buffer, copies it and the images up, and reads the results back with one wait.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import torch

from ..model_config import ModelConfig
from ..geometry import invert_projections
from ..network.postprocess import box_dicts
from ..network.precision import resolve_precision
from ..network.visibility import DEFAULT_MIN_CLEAR
from .execution import CudaGraphStep, load_compiled_step, resolve_budget, resolve_mode
from .history import Frame, FrameHistory, history_geometry
from .step import OnlineStep

LOG = logging.getLogger(__name__)


@dataclass
class Prediction:
    """grid uint8 [X, Y, Z] labels (free = cfg.num_classes); confidence uint8 [X, Y, Z]
    (0..255); boxes: list of dicts (network.postprocess.box_dicts); timings: seconds per stage
    (upload: geometry + images to the device; model: the device step; download: results
    back and into Python objects);
    num_frames: frames the decoder saw; history_reset: why the history restarted, or None;
    observed: bool [X, Y, Z], the voxels a camera sees (None without visibility);
    query_budget: the budget the step ran ("full", or a ``QueryBudget`` name such as
    "s72-d28") and refined_fraction: the share of the queries its later layers refined."""

    grid: np.ndarray
    confidence: np.ndarray
    boxes: list[dict]
    timings: dict[str, float]
    num_frames: int
    history_reset: str | None = None
    query_budget: str = "full"
    refined_fraction: float = 1.0
    observed: np.ndarray | None = None


class OnlinePredictor:
    """Not thread-safe: one worker thread calls ``step``."""

    def __init__(self, model: torch.nn.Module, cfg: ModelConfig, device: str | torch.device,
                 max_gap: float = 1.0, num_frames: int | None = None,
                 min_interval: float = 0.0,
                 precision: str = "fp32", compile: str = "eager", compiled_step=None,
                 visibility: bool = True, query_budget="full",
                 min_clear: float = DEFAULT_MIN_CLEAR):
        """num_frames: history length k (current set included), at most cfg.num_frames
        (None = cfg.num_frames); max_gap: seconds between sets that restart the history;
        min_interval: seconds between the history frames kept, so the decoder sees the
        spacing it was trained with (the dataset's ~0.5 s) whatever the camera rate. The
        current set is always frame 0; it stays in the history only if it is at least
        ``min_interval`` after the last set kept, else the next set takes its place. So kept
        frames are >= min_interval apart, and frame 1 is 0..~2 x min_interval before frame 0
        (training draws 0.33-0.67 s). precision: fp32, or bf16 / fp16 weights and
        autocast for the backbone and decoder (step.OnlineStep; fp16 on CUDA only), or
        auto (bf16 on a CPU with native bf16, else fp32: precision.resolve_precision).
        compile: eager, compiled, graphs (CUDA) or auto (``resolve_mode``); the compile and
        the graph capture happen here, at start-up (``startup_seconds``); compiled_step: a
        .pt2 file of ``odg export --aoti`` run instead of compiling (artifact.py; refused with a
        StaleArtifact if built for another model, configuration, precision, history length,
        device or torch). The grid's free label is the model's class count (cfg.num_classes).
        visibility: also compute which voxels the cameras observe (network/visibility.py);
        min_clear: the least probability that the ray to a voxel is clear for it to count as
        observed (the node's visibility_min_clear; needs a calibrated checkpoint).
        query_budget: full, auto (each step's budget chosen from the one before,
        online/budget_policy.py) or a fraction of the queries (network/budget.py); every
        budget is its own static-shape step, compiled and captured at start-up."""
        k = cfg.num_frames if num_frames is None else int(num_frames)
        if not 1 <= k <= cfg.num_frames:
            raise ValueError(f"history of {k} frames; the model takes 1..{cfg.num_frames}")
        self.model = model.eval()
        self.cfg = cfg
        self.device = torch.device(device)
        self.history = FrameHistory(k, max_gap)
        self.min_interval = float(min_interval)
        # auto -> bf16 or fp32 for this device; an unknown / unusable one fails here
        self.precision = resolve_precision(precision, self.device)
        self.mode = resolve_mode(compile, self.device, compiled_step is not None)
        self.budgets, self.policy = resolve_budget(query_budget, model, cfg)
        if compiled_step is not None and self.budgets != [None]:
            raise ValueError("a compiled step file runs the full query budget only: use "
                             "query_budget full with compiled_step")
        start = time.perf_counter()
        self.visibility = bool(visibility)
        self.min_clear = float(min_clear)
        self.online_step = OnlineStep(model, cfg, k, self.device, self.precision,
                                      visibility=self.visibility,
                                      min_clear=self.min_clear).eval()
        self.ring = self.online_step.ring              # same capacity: slots follow history
        self.layout = self.online_step.layout
        cuda = self.device.type == "cuda"
        H, W = cfg.image_size
        # static inputs: the step (and a captured graph) always reads these device buffers
        self._images_host = torch.zeros(cfg.num_cams, H, W, 3, dtype=torch.uint8,
                                        pin_memory=cuda)
        self._packed_host = torch.zeros(self.layout.size, pin_memory=cuda)
        self._images = self._images_host.to(self.device)
        self._packed = self._packed_host.to(self.device)
        self._function = self.online_step
        # eager on the CPU: the encoder on torch's threads, the rest on one (OnlineStep)
        self.online_step.parallel_encoder_only = self.mode == "eager" and not cuda
        if compiled_step is not None:
            self._function = load_compiled_step(
                compiled_step, self.online_step, model, self.precision, self.visibility,
                self.min_clear, for_cuda_graph=self.mode == "graphs")
        elif self.mode != "eager":
            self._function = torch.compile(self.online_step, fullgraph=True, dynamic=False)
        self._graphs, self._host_outputs = {}, {}
        self._warm_up()
        self.startup_seconds = time.perf_counter() - start
        LOG.info("online step: %s mode%s, start-up (compile / load, capture) %.1f s", self.mode,
                 f" from {compiled_step}" if compiled_step is not None else "",
                 self.startup_seconds)

    def restart_above_speed(self, max_speed: float) -> None:
        """Restart the history where the ego moved between two sets faster than ``max_speed``
        (m/s): a teleport, not a drive (history.FrameHistory)."""
        self.history.max_speed = float(max_speed)

    def reset(self) -> None:
        self.history.clear()
        self.ring.clear()
        if self.policy is not None:
            self.policy.reset()

    @property
    def budget(self):
        """The query budget of the next step (None: the full one)."""
        return self.policy.budget if self.policy is not None else self.budgets[0]

    @torch.inference_mode()
    def _warm_up(self) -> None:
        """Run the step of every budget on blank inputs (compiling each); for graphs,
        capture one CUDA graph per budget after that (in one memory pool: one step runs at a
        time and its outputs are copied out before the next). The ring slot it writes is
        rewritten before any step reads it."""
        k = self.layout.capacity
        self.layout.pack(self._packed_host.numpy(), 0.0, np.broadcast_to(np.eye(4), (k, 4, 4)),
                         0.0, 0, 0)
        self._packed.copy_(self._packed_host)
        if self.mode == "graphs":     # one graph per budget, each captured once
            for budget in self.budgets:
                self._graphs[budget] = CudaGraphStep(
                    lambda images, packed, budget=budget: self._call(images, budget),
                    self._images, self._packed, self.device)
            return
        # on the CPU as ``step`` passes images (a tensor over a NumPy array, made in
        # inference mode): compiled, another kind of tensor would compile a second graph
        images = torch.from_numpy(self._images_host.numpy()) \
            if self.device.type == "cpu" else self._images
        for budget in self.budgets:
            self._call(images, budget)

    def _call(self, images, budget):
        if budget is None:                # the full budget: the step as it always was
            return self._function(images, self._packed)
        return self._function(images, self._packed, budget)

    def _run(self, images: torch.Tensor, budget):
        """The device step of ``budget`` -> its output tensors (a graph reads the static
        buffers and rewrites the same output tensors at every replay)."""
        graph = self._graphs.get(budget)
        if graph is None:
            return self._call(images, budget)
        return graph.replay()

    def _pack_geometry(self, frames, slots, bounds) -> None:
        """History frames (newest first) stored in ring ``slots`` -> the packed buffer, in
        storage-slot order; empty slots get the oldest frame's geometry (finite, never read).
        With the current set's inverse ego2img and image ``bounds`` for its visibility."""
        ego2img, warps, deltas, frame_index = history_geometry(
            frames, slots, self.layout.capacity, self.cfg.num_frames)
        img2ego = invert_projections(frames[0].ego2img) if self.visibility else np.eye(4)
        self.layout.pack(self._packed_host.numpy(), ego2img, warps, deltas, frame_index,
                         slots[0], img2ego, bounds)

    @torch.inference_mode()
    def step(self, images: np.ndarray, ego2img: np.ndarray, pose: np.ndarray,
             stamp: float, bounds=None) -> Prediction:
        """images uint8 [N, H, W, 3] network-input RGB (NumPy, or a tensor on the device);
        ego2img [N, 4, 4] of this set;
        pose [4, 4] T_global_from_ego at ``stamp`` (the set's reference stamp, seconds);
        bounds [N, 4]: each camera's whole image in network-input pixels (u0, v0, u1, v1;
        visibility.image_bounds), None: the network input itself."""
        N = len(images)
        if images.shape[1:] != (*self.cfg.image_size, 3) or N != self.cfg.num_cams:
            raise ValueError(f"images {images.shape}, expected [{self.cfg.num_cams}, "
                             f"{self.cfg.image_size[0]}, {self.cfg.image_size[1]}, 3]")
        t0 = time.perf_counter()
        # the newest kept set is provisional while it is closer than min_interval to the one
        # before it: this set takes its place
        replace = self.history.newest_is_provisional(self.min_interval)
        reset = self.history.push(Frame(features=None, pose=np.asarray(pose, np.float64),
                                        ego2img=np.asarray(ego2img, np.float64),
                                        stamp=float(stamp)), replace_newest=replace)
        if reset is not None:
            self.ring.clear()
            if self.policy is not None:           # a new drive: the full budget first
                self.policy.reset()
        self.ring.advance(replace_newest=replace)
        frames = self.history.frames()
        assert len(frames) == len(self.ring)
        H, W = self.cfg.image_size
        self._pack_geometry(frames, self.ring.slots(),
                            (0.0, 0.0, W, H) if bounds is None else bounds)
        images_in = self._images
        if isinstance(images, torch.Tensor):       # decoded on the device already
            self._images.copy_(images, non_blocking=True)
        elif self.device.type == "cpu" and not self._graphs:
            # the step reads the set's own array: on the CPU, copying it into a static
            # buffer first would only cost time (no graph reads fixed addresses there)
            images_in = torch.from_numpy(np.ascontiguousarray(images, dtype=np.uint8))
        else:
            self._images_host.numpy()[...] = images
            self._images.copy_(self._images_host, non_blocking=True)
        self._packed.copy_(self._packed_host, non_blocking=True)
        t1 = time.perf_counter()

        cuda = self.device.type == "cuda"
        if cuda:   # CUDA events: no synchronize inside the step
            started, finished = (torch.cuda.Event(enable_timing=True) for _ in range(2))
            started.record()
        budget = self.budget
        outputs = self._run(images_in, budget)
        if cuda:
            finished.record()
            for host, value in zip(self._host_outputs_for(budget, outputs), outputs):
                host.copy_(value, non_blocking=True)
            copied = torch.cuda.Event()
            copied.record()
            copied.synchronize()                          # the step's only wait
            outputs = self._host_outputs[budget]
        t2 = time.perf_counter()
        rewritten = cuda or bool(self._graphs)
        labels, confidence, boxes, score, label, valid, observed, *needed = (
            # copies of their own where the next step rewrites the buffers (the pinned host
            # copies, a graph's outputs); the CPU step's outputs are new tensors each time
            o.numpy().copy() if rewritten else o.numpy() for o in outputs)
        X, Y, Z = self.cfg.grid_shape
        boxes = box_dicts(boxes, score, label, valid)
        if self.policy is not None:
            self.policy.update(int(needed[0][0]), int(needed[0][1]), len(boxes))
        model_seconds = started.elapsed_time(finished) / 1e3 if cuda else t2 - t1
        timings = {"upload": t1 - t0, "model": model_seconds,
                   "download": max(0.0, time.perf_counter() - t1 - model_seconds)}
        return Prediction(grid=labels.reshape(X, Y, Z), confidence=confidence.reshape(X, Y, Z),
                          boxes=boxes, timings=timings, num_frames=len(frames),
                          history_reset=reset, query_budget=self._budget_name(budget),
                          refined_fraction=self._refined_fraction(budget),
                          observed=observed.reshape(X, Y, Z).astype(bool)
                          if self.visibility else None)

    def _budget_name(self, budget) -> str:
        return "full" if budget is None else budget.name

    def _refined_fraction(self, budget) -> float:
        return 1.0 if budget is None else budget.refined_fraction(self.cfg)

    def _host_outputs_for(self, budget, outputs):
        if budget not in self._host_outputs:
            self._host_outputs[budget] = [torch.empty_like(o, device="cpu").pin_memory()
                                          for o in outputs]
        return self._host_outputs[budget]
