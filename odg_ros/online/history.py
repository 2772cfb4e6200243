"""Rolling history of the last k frames for the temporal decoder (OPUS-style feature cache).

Each frame's backbone features are computed once, when it is the newest frame, and reused
by the next k-1 decodes (the predictor keeps them in the model's FeatureRing). A frame keeps
what the decoder needs to look back at it: its ego pose, its ego->image matrices and its
stamp. The history starts over when time runs
backwards (a bag loop, a replayed set) or jumps forward by more than ``max_gap`` seconds
(dropped input), or when the ego moved between two frames faster than ``max_speed`` (a
teleport: relocalisation): frames across such a break would be warped with a meaningless
ego motion.

Plain Python and NumPy (no torch import): the host side of an exported step uses it too
(onnx_inputs.py).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from ..geometry import invert_transforms

if TYPE_CHECKING:
    import torch


@dataclass
class Frame:
    """One processed camera set.

    features  list of L tensors [1, N, C, H_l, W_l] (model.extract_features of this set),
              or None where a network.feature_ring.FeatureRing holds them (the predictor)
    pose      float64 [4, 4] T_global_from_ego at the set's reference stamp
    ego2img   float64 [N, 4, 4] this frame's ego -> network-input pixels
    stamp     seconds (the set's reference stamp)
    """

    features: list[torch.Tensor] | None
    pose: np.ndarray
    ego2img: np.ndarray
    stamp: float


class FrameHistory:
    """Newest-first list of at most ``capacity`` frames."""

    def __init__(self, capacity: int, max_gap: float = 1.0, max_speed: float = math.inf):
        if capacity < 1 or not max_gap > 0 or not max_speed > 0:
            raise ValueError(f"bad history settings: capacity={capacity}, max_gap={max_gap}, "
                             f"max_speed={max_speed}")
        self.capacity = int(capacity)
        self.max_gap = float(max_gap)
        self.max_speed = float(max_speed)
        self._frames: deque[Frame] = deque(maxlen=self.capacity)
        self.resets = {"time_backwards": 0, "gap": 0, "teleport": 0}

    def __len__(self) -> int:
        return len(self._frames)

    def clear(self) -> None:
        self._frames.clear()

    def push(self, frame: Frame, replace_newest: bool = False) -> str | None:
        """Add the newest frame (or, with ``replace_newest``, put it in place of the newest);
        returns the reason the history was reset first, or None."""
        reason = None
        if self._frames:
            newest = self._frames[0].stamp
            if frame.stamp <= newest:
                reason = "time_backwards"
            elif frame.stamp - newest > self.max_gap:
                reason = "gap"
            elif not (np.linalg.norm(frame.pose[:3, 3] - self._frames[0].pose[:3, 3])
                      <= self.max_speed * (frame.stamp - newest)):
                reason = "teleport"
        if reason is not None:
            self.resets[reason] += 1
            self._frames.clear()
        if replace_newest and self._frames:
            self._frames[0] = frame
        else:
            self._frames.appendleft(frame)
        return reason

    def frames(self) -> list[Frame]:
        """Frames newest first (index 0 = current)."""
        return list(self._frames)

    def newest_is_provisional(self, min_interval: float) -> bool:
        """Whether the newest frame is closer than ``min_interval`` (s) to the one before it:
        then the next set takes its place (``push(replace_newest=True)``), so the frames kept
        stay at least ``min_interval`` apart."""
        frames = self._frames
        return len(frames) > 1 and frames[0].stamp - frames[1].stamp < min_interval


def history_geometry(frames: Sequence[Frame], slots: Sequence[int], capacity: int,
                     num_frames: int):
    """The decoder's geometry of history ``frames`` (newest first) stored in ring ``slots``
    (one each, newest first) of a ring of ``capacity`` slots, in storage-slot order:

    ego2img float64 [capacity, N, 4, 4]  each frame's ego -> network-input pixels
    ego_warp float64 [capacity, 4, 4]    T_ego(frame)_from_ego(current) = P_frame^-1 P_current
    time_delta float64 [capacity]        current stamp - frame stamp (s)
    frame_index list[int] [num_frames]   the slot each of the model's time steps reads; a
                                         step beyond the frames kept repeats the oldest

    Empty slots get the oldest frame's geometry (finite; no time step reads them)."""
    current, oldest = frames[0], frames[-1]
    N = len(current.ego2img)
    # the warps of all frames in one stacked computation
    frame_warps = invert_transforms(np.stack([f.pose for f in frames])) @ current.pose
    ego2img = np.broadcast_to(oldest.ego2img, (capacity, N, 4, 4)).copy()
    warps = np.broadcast_to(frame_warps[-1], (capacity, 4, 4)).copy()
    deltas = np.full(capacity, current.stamp - oldest.stamp)
    for frame, slot, warp in zip(frames, slots, frame_warps):
        ego2img[slot] = frame.ego2img
        warps[slot] = warp
        deltas[slot] = current.stamp - frame.stamp
    frame_index = list(slots) + [slots[-1]] * (num_frames - len(slots))
    return ego2img, warps, deltas, frame_index
