"""Streaming inference: one camera set in, one occupancy grid + box list out.

The backbone runs on the newest set only; its features are written once into the model's
FeatureRing (already in the sampling layout) and the rolling history (history.py) keeps each
set's pose, ego->image matrices and stamp. The decoder looks at the cached features of the
last k sets, with the ego motion between them (ego_warp = P_t^-1 P_0) and their time
differences. This gives the
same result as running the model offline over the same k sets (test_online_predictor.py),
at the cost of one backbone pass per set instead of k.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..config import ModelConfig
from ..geometry import ego_warp
from ..network.feature_ring import FeatureRing
from ..network.outputs import ODGOutput
from ..network.padding import pad_occupancy
from ..network.postprocess import box_list, occupancy_grid
from ..network.precision import precision_context
from ..preprocess import normalize
from .history import Frame, FrameHistory


@dataclass
class Prediction:
    """grid uint8 [X, Y, Z] labels (17 free); confidence uint8 [X, Y, Z] (0..255);
    boxes: list of dicts (network.postprocess.box_list); timings: seconds per stage;
    num_frames: frames the decoder saw; history_reset: why the history restarted, or None."""

    grid: np.ndarray
    confidence: np.ndarray
    boxes: list[dict]
    timings: dict[str, float]
    num_frames: int
    history_reset: str | None = None
    output: ODGOutput | None = field(default=None, repr=False)


class OnlinePredictor:
    """Not thread-safe: one worker thread calls ``step``."""

    def __init__(self, model: torch.nn.Module, cfg: ModelConfig, device: str | torch.device,
                 max_gap: float = 1.0, num_frames: int | None = None,
                 keep_output: bool = False, min_interval: float = 0.0,
                 precision: str = "fp32"):
        """num_frames: history length k (current set included), at most cfg.num_frames
        (None = cfg.num_frames); max_gap: seconds between sets that restart the history;
        min_interval: seconds between the history frames kept, so the decoder sees the
        spacing it was trained with (the dataset's ~0.5 s) whatever the camera rate. The
        current set is always frame 0; it stays in the history only if it is at least
        ``min_interval`` after the last set kept, else the next set takes its place. So kept
        frames are >= min_interval apart, and frame 1 is 0..~2 x min_interval before frame 0
        (training draws 0.33-0.67 s). precision: fp32, or bf16 / fp16 autocast for the
        backbone and decoder (network.precision; fp16 on CUDA only)."""
        k = cfg.num_frames if num_frames is None else int(num_frames)
        if not 1 <= k <= cfg.num_frames:
            raise ValueError(f"history of {k} frames; the model takes 1..{cfg.num_frames}")
        self.model = model.eval()
        self.cfg = cfg
        self.device = torch.device(device)
        self.history = FrameHistory(k, max_gap)
        self.ring = FeatureRing(k, cfg.num_groups)     # same capacity: slots follow history
        self.keep_output = keep_output   # tests compare the raw network output
        self.min_interval = float(min_interval)
        precision_context(precision, self.device)      # an unknown / unusable one fails here
        self.precision = precision

    def reset(self) -> None:
        self.history.clear()
        self.ring.clear()

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @torch.inference_mode()
    def step(self, images: np.ndarray, ego2img: np.ndarray, pose: np.ndarray,
             stamp: float) -> Prediction:
        """images uint8 [N, H, W, 3] network-input RGB; ego2img [N, 4, 4] of this set;
        pose [4, 4] T_global_from_ego at ``stamp`` (the set's reference stamp, seconds)."""
        N = len(images)
        if images.shape[1:] != (*self.cfg.image_size, 3) or N != self.cfg.num_cams:
            raise ValueError(f"images {images.shape}, expected [{self.cfg.num_cams}, "
                             f"{self.cfg.image_size[0]}, {self.cfg.image_size[1]}, 3]")
        timings = {}
        t0 = time.perf_counter()
        x = normalize(torch.from_numpy(np.ascontiguousarray(images)).to(self.device))
        self._sync()
        t1 = time.perf_counter()
        timings["decode_images"] = t1 - t0
        with precision_context(self.precision, self.device):
            features = self.model.extract_features(x.unsqueeze(0))   # L x [1, N, C, h, w]
        self._sync()
        t2 = time.perf_counter()
        timings["backbone"] = t2 - t1

        # the newest kept set is provisional while it is closer than min_interval to the one
        # before it: this set takes its place
        kept = self.history.frames()
        replace = len(kept) > 1 and kept[0].stamp - kept[1].stamp < self.min_interval
        reset = self.history.push(Frame(features=None, pose=np.asarray(pose, np.float64),
                                        ego2img=np.asarray(ego2img, np.float64),
                                        stamp=float(stamp)), replace_newest=replace)
        if reset is not None:
            self.ring.clear()
        self.ring.push(features, replace_newest=replace)
        frames = self.history.frames()
        assert len(frames) == len(self.ring)
        current = frames[0]
        warps = np.stack([ego_warp(current.pose, f.pose) for f in frames])
        deltas = np.array([current.stamp - f.stamp for f in frames])

        def as_tensor(array):
            return torch.as_tensor(array, dtype=torch.float32, device=self.device)

        with precision_context(self.precision, self.device):
            output = self.model.decode_ring(
                self.ring,
                as_tensor(np.stack([f.ego2img for f in frames]))[None],   # [1, T, N, 4, 4]
                as_tensor(warps)[None],                                   # [1, T, 4, 4]
                as_tensor(deltas)[None])                                  # [1, T]
        self._sync()
        t3 = time.perf_counter()
        timings["decoder"] = t3 - t2

        grid, confidence = occupancy_grid(output, self.cfg)
        if self.cfg.occupancy_padding:
            grid, confidence = pad_occupancy(grid, confidence, self.cfg.num_classes,
                                             self.cfg.score_threshold)
        boxes = box_list(output, self.cfg)[0]
        grid, confidence = grid[0].cpu().numpy(), confidence[0].cpu().numpy()
        timings["postprocess"] = time.perf_counter() - t3
        return Prediction(grid=grid, confidence=confidence, boxes=boxes, timings=timings,
                          num_frames=len(frames), history_reset=reset,
                          output=output if self.keep_output else None)
