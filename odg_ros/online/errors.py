"""The one exception of the online pipeline: an input that cannot be used.

Every reason a camera set is skipped has a short ``kind`` (a diagnostics counter name and
the name of the throttled warning) and a human message. The node catches ``BadInput``,
logs it, counts it and keeps running; nothing else is caught, so programming errors still
surface.
"""
from __future__ import annotations

# Every kind the pipeline raises or counts; diagnostics report each of them (zeros included)
# so a dashboard sees the same keys from the first message on.
BAD_INPUT_KINDS = (
    "corrupt_image",        # undecodable / truncated JPEG or PNG, short raw buffer
    "unsupported_encoding",  # raw encoding or compressed format we do not decode
    "wrong_image_size",     # decoded size differs from the CameraInfo
    "missing_camera_info",  # no CameraInfo received for a camera of the set (after pose_wait)
    "bad_camera_info",      # CameraInfo with a zero / non-finite K or zero size
    "implausible_camera_info",  # focal length / principal point out of range for the size
    "bad_pose",             # NaN or non-orthonormal pose
    "implausible_motion",   # pose sample faster / accelerating more than a car can: a glitch
    "bad_tf",               # TF link that would close a loop
    "pose_miss",            # no pose at a camera stamp: outside the buffer, across a gap
                            # wider than max_pose_gap, or still missing after pose_wait
    "missing_extrinsics",   # no base_link -> camera transform (after pose_wait)
    "future_stamp",         # image stamp ahead of the node clock
    "bad_stamp",            # header stamp that is no valid time (nanosec outside [0, 1e9))
    "image_too_large",      # encoded header declares more pixels than max_image_pixels
    "unknown_camera",       # message from a camera not in the configured list
)


class BadInput(Exception):
    """An unusable input. ``kind`` is one of ``BAD_INPUT_KINDS``.

    ``pending``: the look-up failed only because its data has not arrived yet (a pose or
    transform newer than any received, within the gap interpolation may bridge): the set
    may wait for it, as tf2's message filter holds a message, instead of being skipped."""

    def __init__(self, kind: str, message: str, pending: bool = False):
        if kind not in BAD_INPUT_KINDS:
            raise ValueError(f"unknown bad-input kind {kind!r}")
        super().__init__(message)
        self.kind = kind
        self.message = message
        self.pending = bool(pending)

    def __str__(self) -> str:
        return f"{self.kind}: {self.message}"
