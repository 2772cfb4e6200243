"""A ring buffer of cached history features in the sampling layout (the online fast path).

``ODG.decode`` lays all T frames out for sampling at every step (one copy of the whole
history). The ring keeps them laid out: each frame is written once, into the slot of the
oldest one, when it is pushed; ``ODG.decode_ring`` samples the slots in place and reads them
in time order through a frame index. Memory: ``capacity`` frames per level, allocated at the
first push (the zero rows of the camera-rows layout are never written).
"""
from __future__ import annotations

import torch

from .sampling import camera_rows_layout, camera_rows_view, layout_dtype


class FeatureRing:
    def __init__(self, capacity: int, num_groups: int):
        if capacity < 1 or num_groups < 1:
            raise ValueError(f"bad ring: capacity={capacity}, num_groups={num_groups}")
        self.capacity = int(capacity)
        self.num_groups = int(num_groups)
        self._memory: list[torch.Tensor] | None = None   # L x [S*B*G, N*(h+1), w, c]
        self._shapes = None
        self._head = -1                                   # slot of the newest frame
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def clear(self) -> None:
        """Forget the cached frames (keeps the memory: slots are overwritten before use)."""
        self._head, self._count = -1, 0

    def push(self, features: list[torch.Tensor], replace_newest: bool = False) -> None:
        """features: L levels [B, N, C, h, w] of the newest frame (``ODG.extract_features``).
        replace_newest: overwrite the newest frame instead of adding one (the online history
        keeps a frame only when it is far enough from the last one kept)."""
        shapes = [tuple(f.shape) for f in features]
        if self._memory is None:
            self._allocate(features)
        elif shapes != self._shapes or features[0].device != self._memory[0].device or \
                layout_dtype(features[0].dtype) != self._memory[0].dtype:
            raise ValueError(f"feature shapes {shapes} ({features[0].dtype} on "
                             f"{features[0].device}) differ from the ring's {self._shapes} "
                             f"({self._memory[0].dtype} on {self._memory[0].device})")
        if not (replace_newest and self._count):
            self._head = (self._head + 1) % self.capacity
            self._count = min(self._count + 1, self.capacity)
        for f, memory in zip(features, self._memory):
            per_slot = memory.shape[0] // self.capacity
            camera_rows_layout([f.detach()], self.num_groups,
                               out=memory[self._head * per_slot:(self._head + 1) * per_slot])

    def slots(self) -> list[int]:
        """Storage slot of each cached frame, newest first."""
        return [(self._head - t) % self.capacity for t in range(self._count)]

    def levels(self) -> list[torch.Tensor]:
        """L levels [F*B*G, c, N*(h+1), w] over the F filled slots, in storage order."""
        if self._memory is None:
            return []
        filled = []
        for memory in self._memory:
            per_slot = memory.shape[0] // self.capacity
            filled.append(camera_rows_view(memory[:self._count * per_slot]))
        return filled

    def _allocate(self, features) -> None:
        G = self.num_groups
        self._shapes = [tuple(f.shape) for f in features]
        self._memory = []
        for f in features:
            B, N, C, h, w = f.shape
            if C % G:
                raise ValueError(f"{C} channels do not split into {G} groups")
            self._memory.append(f.new_zeros(self.capacity * B * G, N * (h + 1), w, C // G,
                                            dtype=layout_dtype(f.dtype)))
