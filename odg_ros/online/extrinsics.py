"""Where each camera's extrinsics (T_ego_from_cam) come from: TF, the rig file, or TF when the
data carries it and the rig file otherwise (``auto``, the node's default).

A rig file is one car's calibration; a bag from another car runs with wrong extrinsics unless
they follow the bag. With ``auto`` a camera takes TF (``base_frame`` -> its CameraInfo's
frame_id, static or dynamic) as soon as TF joins those frames, and the rig file only while
TF does not:

* before any TF has joined them, a set waits for it like for a pose not received yet
  (``pending``, bounded by the node's ``pose_wait``): a bag with only dynamic /tf at 2 Hz
  can complete its first set before its first /tf, and a set must not be computed with the
  rig file while the next one uses TF. When a set's wait runs out (``settle``) the camera
  takes the rig file, logged once;
* if TF for that camera appears later, it wins from then on (TF follows the bag), logged
  once with the time it was rig-based;
* where both exist and differ by more than ``max_translation`` metres or ``max_rotation``
  degrees, one warning per camera names it, the difference and the one used (TF).

``rig`` and ``tf`` use only the one source. Thread-safe (the pipeline's decoding thread
looks up, the diagnostics timer reads ``sources``).
"""
from __future__ import annotations

import math
import threading
from typing import Callable

import numpy as np

from ..geometry import invert_transform
from .errors import BadInput
from .camera_calibration import Rig
from .transforms import TransformBuffer

SOURCES = ("auto", "rig", "tf")


def transform_difference(T_a, T_b) -> tuple[float, float]:
    """(translation distance m, rotation angle deg) between two rigid transforms."""
    delta = invert_transform(np.asarray(T_a, np.float64)) @ np.asarray(T_b, np.float64)
    cos = (np.trace(delta[:3, :3]) - 1.0) / 2.0
    angle = math.degrees(math.acos(min(1.0, max(-1.0, cos))))
    return float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])), angle


class CameraExtrinsics:
    """``extrinsics(camera, frame_id, stamp)`` -> T_ego_from_cam for the pipeline.

    source: auto | tf | rig; tf: the node's TransformBuffer (None with rig); rig: the rig file
    (None: none, e.g. tf); log(level, message): where the once-per-camera notes go ('info' or
    'warning')."""

    def __init__(self, source: str, base_frame: str, tf: TransformBuffer | None = None,
                 rig: Rig | None = None,
                 log: Callable[[str, str], None] = lambda level, message: None,
                 max_translation: float = 0.05, max_rotation: float = 0.5):
        if source not in SOURCES:
            raise ValueError(f"extrinsics_source {source!r}: expected one of: "
                             f"{', '.join(SOURCES)}")
        if source != "rig" and tf is None:
            raise ValueError(f"extrinsics_source {source} needs a TF buffer")
        if source == "rig" and rig is None:
            raise ValueError("extrinsics_source rig needs a rig file")
        self.source = source
        self.base_frame = base_frame
        self.tf = tf
        self.rig = rig
        self._log = log
        self.max_translation = float(max_translation)
        self.max_rotation = float(max_rotation)
        self._lock = threading.Lock()
        self._used: dict[str, str] = {}        # camera -> "tf" | "rig file" (auto and tf)
        self._settled: set[str] = set()        # auto: cameras that gave up waiting for TF
        self._compared: set[str] = set()

    def __call__(self, camera: str, frame_id: str, stamp: float) -> np.ndarray:
        if self.source == "rig":
            return self._from_rig(camera)
        if self.source == "tf" or self.tf.connected(self.base_frame, frame_id):
            T = self.tf.lookup(self.base_frame, frame_id, stamp, "missing_extrinsics")
            self._using_tf(camera, frame_id, T)
            return T
        with self._lock:
            settled = camera in self._settled
            used = self._used.get(camera)
        if used == "tf":
            # TF carried this camera and stopped (its frame forgotten): wait for it again
            # rather than switch silently to another car's calibration
            return self.tf.lookup(self.base_frame, frame_id, stamp, "missing_extrinsics")
        if not settled:
            raise BadInput("missing_extrinsics", f"no TF {self.base_frame} -> {frame_id} "
                           f"for {camera} yet (extrinsics_source auto: the rig file once a "
                           "set has waited pose_wait)", pending=True)
        T = self._from_rig(camera)
        with self._lock:
            self._used[camera] = "rig file"
        return T

    def settle(self, camera: str, frame_id: str) -> None:
        """A set waited in vain for this camera's TF: with auto, the rig file from now on
        (until TF carries the camera)."""
        if self.source != "auto" or self.tf.connected(self.base_frame, frame_id):
            return
        with self._lock:
            if camera in self._settled or self._used.get(camera) == "tf":
                return
            self._settled.add(camera)
        if self.rig is not None and camera in self.rig.cameras:
            self._log("info", f"{camera}: no TF {self.base_frame} -> {frame_id} in the data: "
                      "its extrinsics come from the rig file")

    def sources(self, cameras) -> dict[str, str]:
        """camera -> where its extrinsics come from now, for the diagnostics."""
        with self._lock:
            if self.source == "rig":
                return {c: "rig file" for c in cameras}
            return {c: self._used.get(c, "none yet (waiting for TF)" if self.source == "auto"
                                      and c not in self._settled else "none yet")
                    for c in cameras}

    # ---------------------------------------------------------------------------------
    def _from_rig(self, camera: str) -> np.ndarray:
        if self.rig is None or camera not in self.rig.cameras:
            raise BadInput("missing_extrinsics", f"{camera} is not in the rig file" + (
                f" and TF has no {self.base_frame} -> its frame" if self.source == "auto"
                else ""))
        return self.rig.cameras[camera].sensor2ego

    def _using_tf(self, camera: str, frame_id: str, T: np.ndarray) -> None:
        with self._lock:
            previous = self._used.get(camera)
            self._used[camera] = "tf"
            compare = self.source == "auto" and camera not in self._compared
            self._compared.add(camera)
        if previous == "rig file":
            self._log("warning", f"{camera}: TF {self.base_frame} -> {frame_id} arrived after "
                      "sets used the rig file; TF from now on (it follows the data)")
        if not compare or self.rig is None or camera not in self.rig.cameras:
            return
        distance, angle = transform_difference(T, self.rig.cameras[camera].sensor2ego)
        if distance > self.max_translation or angle > self.max_rotation:
            self._log("warning", f"{camera}: TF {self.base_frame} -> {frame_id} differs from "
                      f"the rig file by {distance:.3f} m and {angle:.2f} deg; using TF, which "
                      "follows the data (another car's calibration than the rig file's?)")
