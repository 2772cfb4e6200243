"""A ring buffer of cached history features in the sampling layout (the online fast path).

``ODG.decode`` lays all T frames out for sampling at every step (one copy of the whole
history). The ring keeps them laid out: each frame is written once, into the slot of the
oldest one, when it is pushed; ``ODG.decode_ring`` samples the slots in place and reads them
in time order through a frame index. Memory: ``capacity`` frames per level, allocated at the
first push (the zero rows of the camera-rows layout are never written).

Static shapes (the compiled online step): ``advance`` does the bookkeeping on the host and
returns the slot to write; ``write_slot`` writes it with the slot in a device tensor and
``all_levels`` gives all ``capacity`` slots whatever the fill level, so every step has the
same shapes; the frame index says which slots the decoder reads.
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
        self.check(features)
        slot = self.advance(replace_newest)
        for f, memory in zip(features, self._memory):
            per_slot = memory.shape[0] // self.capacity
            camera_rows_layout([f.detach()], self.num_groups,
                               out=memory[slot * per_slot:(slot + 1) * per_slot])

    def check(self, features: list[torch.Tensor]) -> None:
        """Allocate the memory for ``features`` at the first call; later ones must match."""
        shapes = [tuple(f.shape) for f in features]
        if self._memory is None:
            self._allocate(features)
        elif shapes != self._shapes or features[0].device != self._memory[0].device or \
                layout_dtype(features[0].dtype) != self._memory[0].dtype:
            raise ValueError(f"feature shapes {shapes} ({features[0].dtype} on "
                             f"{features[0].device}) differ from the ring's {self._shapes} "
                             f"({self._memory[0].dtype} on {self._memory[0].device})")

    def advance(self, replace_newest: bool = False) -> int:
        """Host bookkeeping of a push: -> the storage slot the newest frame goes to."""
        if not (replace_newest and self._count):
            self._head = (self._head + 1) % self.capacity
            self._count = min(self._count + 1, self.capacity)
        return self._head

    def write_slot(self, features: list[torch.Tensor], slot: torch.Tensor) -> None:
        """Write ``features`` (as for ``push``) into storage slot ``slot`` (long [1], on the
        device): the same shapes and no host read whichever slot it is."""
        G = self.num_groups
        for f, memory in zip(features, self._memory):
            B, N, C, h, w = f.shape
            rows = memory.view(self.capacity, B, G, N, h + 1, w, C // G)[:, :, :, :, 1:]
            # the camera-rows layout of one frame, below the zero rows left as allocated
            rows.index_copy_(0, slot, f.detach().view(B, N, G, C // G, h, w)
                             .permute(0, 2, 1, 4, 5, 3).unsqueeze(0).to(memory.dtype))

    def all_levels(self) -> list[torch.Tensor]:
        """L levels [capacity*B*G, c, N*(h+1), w] over every slot, filled or not."""
        return [camera_rows_view(memory) for memory in self._memory or []]

    @property
    def memory(self) -> list[torch.Tensor]:
        """The storage of every level, L x [capacity*B*G, N*(h+1), w, c] (none before the
        first push): what a compiled or exported step takes as inputs and writes in place."""
        return list(self._memory or [])

    def use_memory(self, memory: list[torch.Tensor]) -> None:
        """Read and write ``memory`` (laid out as ``memory``) from now on: the compiled and
        exported steps pass the ring's storage in as their inputs."""
        self._memory = list(memory)

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
