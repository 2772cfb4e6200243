"""odg_node's set-up without ROS: from the validated parameters to the TF buffer, the ego pose
look-up, the camera extrinsics, the intrinsics of a rig file and the pipeline.

The node (odg_ros/ros/node.py) builds itself from here, and so does testing/bag_pipeline.py,
which runs a bag through the pipeline deterministically: both see the same settings, so a
parameter added to one cannot be missed by the other.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

from ..resources import resource_path
from .diagnostics import PipelineStats
from .errors import BadInput
from .extrinsics import CameraExtrinsics
from .pipeline import OnlinePipeline, PipelineSettings
from .predictor import OnlinePredictor
from .camera_calibration import CameraCalibration, load_rig
from .transforms import TransformBuffer

SHIPPED_RIG = "config/rig_nuscenes.yaml"


@dataclass
class Sources:
    """Where the node's geometry comes from. pose_lookup: T_global_from_ego at a stamp from
    TF, or None (odometry: the pipeline's own pose buffer); intrinsics: camera -> its
    calibration from the rig file (intrinsics_source rig), None where CameraInfo gives it."""

    tf: TransformBuffer
    pose_lookup: Callable[[float], object] | None
    extrinsics: CameraExtrinsics
    intrinsics: dict[str, CameraCalibration] | None

    def camera_frames(self) -> set[str]:
        """The camera frames known at start (from the rig file's intrinsics), else none."""
        return {c.frame_id for c in (self.intrinsics or {}).values()}


def sources(p: dict, cameras: list[str], log=lambda level, message: None,
            clock: Callable[[], float] = time.monotonic) -> Sources:
    """The Sources of the validated parameters ``p``. ``log(level, message)`` takes the
    extrinsics' notes; ``clock`` ages the TF cache (steady in the node; bag time when a bag
    is run without a player). A configuration that cannot work raises ValueError (one line)."""
    tf = TransformBuffer(max_extrapolation=float(p["max_pose_extrapolation"]),
                         max_interpolation_gap=float(p["max_pose_gap"]),
                         cache_time=float(p["tf_cache_time"]), max_speed=float(p["max_speed"]),
                         max_acceleration=float(p["max_acceleration"]), clock=clock)
    pose_lookup = None
    if p["pose_source"] == "tf":
        global_frame, base = p["global_frame"], p["base_frame"]
        pose_lookup = lambda t: tf.lookup(global_frame, base, t, "pose_miss")  # noqa: E731
    needs_rig = p["extrinsics_source"] != "tf" or p["intrinsics_source"] == "rig"
    rig = load_rig(p["rig_file"] or resource_path(SHIPPED_RIG)) if needs_rig else None
    missing = [c for c in cameras if rig is not None and c not in rig.cameras]
    if missing and (p["extrinsics_source"] == "rig" or p["intrinsics_source"] == "rig"):
        uses = " and ".join(f"{what}_source rig" for what in ("intrinsics", "extrinsics")
                            if p[f"{what}_source"] == "rig")
        raise ValueError(f"cameras {missing} are not in the rig file {_rig_name(p)} ({uses}; "
                         f"it has {list(rig.cameras)}); `odg bag rig` writes one for a bag "
                         "layout's camera names")
    if missing:
        log("warning", f"cameras {missing} are not in the rig file: their extrinsics "
            "can only come from TF")
    extrinsics = CameraExtrinsics(p["extrinsics_source"], p["base_frame"], tf,
                                  rig if p["extrinsics_source"] != "tf" else None, log)
    intrinsics = None
    if p["intrinsics_source"] == "rig":
        intrinsics = {c: rig.cameras[c] for c in cameras}
    return Sources(tf, pose_lookup, extrinsics, intrinsics)


def _rig_name(p: dict) -> str:
    return p["rig_file"] or SHIPPED_RIG


def build_pipeline(predictor: OnlinePredictor, p: dict, cameras: list[str], found: Sources,
                   stats: PipelineStats | None = None,
                   clock: Callable[[], float] | None = None) -> OnlinePipeline:
    """The pipeline of the validated parameters around ``predictor``, with the rig file's
    intrinsics already given where intrinsics_source is rig (then no CameraInfo is read).
    ``clock``: the node's clock, which measures the bounded wait (pose_wait)."""
    pipeline = OnlinePipeline(predictor, PipelineSettings.from_parameters(cameras, p),
                              found.extrinsics, found.pose_lookup, stats, clock=clock)
    for camera, calibration in (found.intrinsics or {}).items():
        try:
            pipeline.on_camera_info(camera, calibration.intrinsics, *calibration.image_hw,
                                    calibration.frame_id)
        except BadInput as error:     # plausible for load_rig, not for the node's bounds
            pipeline.close()
            raise ValueError(f"rig file {_rig_name(p)}, camera {camera} (intrinsics_source "
                             f"rig): {error.message}") from None
    return pipeline

