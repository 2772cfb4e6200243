"""A small TF buffer (the content of /tf and /tf_static) without tf2_ros.

tf2_ros has no PyPI wheel, and the node needs only two kinds of lookups: the ego pose
(e.g. map -> base_link, possibly through odom) at each camera stamp and the camera
extrinsics (base_link -> camera frame, usually static). This buffer keeps the transform
tree the TF messages describe (one parent per child, as TF requires): a static edge is one
transform, a dynamic edge a PoseBuffer (interpolation + the same no-extrapolation bound as
odometry). A lookup composes the edges along the path between the two frames, each at the
requested stamp. Thread-safe.
"""
from __future__ import annotations

import threading

import numpy as np

from ..geometry import invert_transform, is_rigid
from .errors import BadInput
from .poses import PoseBuffer


class TransformBuffer:
    def __init__(self, max_extrapolation: float = 0.05, time_jump: float = 1.0,
                 capacity: int = 2000):
        self.max_extrapolation = max_extrapolation
        self.time_jump = time_jump
        self.capacity = capacity
        self._parent: dict[str, str] = {}                 # child -> parent
        self._static: dict[str, np.ndarray] = {}          # child -> T_parent_from_child
        self._dynamic: dict[str, PoseBuffer] = {}         # child -> buffer of T_parent_from_child
        self._lock = threading.Lock()

    def add(self, parent: str, child: str, stamp: float, T_parent_from_child,
            static: bool = False) -> None:
        """One transform of a TFMessage. Raises BadInput('bad_pose') if it is not rigid."""
        T = np.asarray(T_parent_from_child, dtype=np.float64)
        if not parent or not child or parent == child:
            raise BadInput("bad_pose", f"transform with frames {parent!r} -> {child!r}")
        if not is_rigid(T):
            raise BadInput("bad_pose", f"transform {parent} -> {child} is not a finite rigid "
                           "transform")
        with self._lock:
            if self._parent.get(child, parent) != parent:
                # TF allows one parent per frame; a re-parented frame restarts its edge.
                self._static.pop(child, None)
                self._dynamic.pop(child, None)
            self._parent[child] = parent
            if static:
                self._static[child] = T
                self._dynamic.pop(child, None)
            else:
                buffer = self._dynamic.get(child)
                if buffer is None:
                    buffer = self._dynamic[child] = PoseBuffer(
                        self.capacity, self.max_extrapolation, time_jump=self.time_jump)
                self._static.pop(child, None)
                buffer.add(stamp, T)

    def frames(self) -> set[str]:
        with self._lock:
            return self._frames_unlocked()

    def _frames_unlocked(self) -> set[str]:
        return set(self._parent) | set(self._parent.values())

    def _chain_to_root(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self._parent:
            chain.append(self._parent[chain[-1]])
            if len(chain) > 64:
                raise BadInput("missing_extrinsics", f"TF loop at {frame!r}")
        return chain

    def _root_from(self, chain: list[str], stamp: float, kind: str) -> np.ndarray:
        """T_root_from_chain[0] at ``stamp`` (composition along the chain)."""
        T = np.eye(4)
        for child in chain[:-1]:
            if child in self._static:
                edge = self._static[child]
            else:
                try:
                    edge = self._dynamic[child].lookup(stamp)
                except BadInput as error:
                    raise BadInput(kind, f"TF {self._parent[child]} -> {child}: "
                                   f"{error.message}") from None
            T = edge @ T
        return T

    def lookup(self, target: str, source: str, stamp: float,
               kind: str = "pose_miss") -> np.ndarray:
        """T_target_from_source at ``stamp``; raises BadInput(kind) if not connected/known."""
        with self._lock:
            if target == source:
                return np.eye(4)
            up_source = self._chain_to_root(source)
            up_target = self._chain_to_root(target)
            common = next((f for f in up_source if f in set(up_target)), None)
            if common is None:
                raise BadInput(kind, f"no TF path between {target!r} and {source!r} "
                               f"(known frames: {sorted(self._frames_unlocked())})")
            to_common_source = up_source[:up_source.index(common) + 1]
            to_common_target = up_target[:up_target.index(common) + 1]
            common_from_source = self._root_from(to_common_source, stamp, kind)
            common_from_target = self._root_from(to_common_target, stamp, kind)
            return invert_transform(common_from_target) @ common_from_source
