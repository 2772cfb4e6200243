"""The nuScenes -> ROS bag converters users run, as far as the node's settings depend on them
(docs/bags.md has their topics, frames, rates and quirks, and config/bags/ the node's
settings for each): how each names the six cameras in its topics and frames.

A rig file for a bag (``odg bag rig --layout NAME``) keys the cameras by the converter's
names (the node's ``camera_names`` fill its topic patterns) and gives them the converter's
frame ids (the node looks up ``base_link -> frame`` in TF).
"""
from __future__ import annotations

from dataclasses import dataclass

from ..nuscenes_cameras import CAMERA_NAMES


@dataclass(frozen=True)
class Converter:
    """camera / frame: format strings of the nuScenes channel (``{channel}``: CAM_FRONT,
    ``{lower}``: cam_front)."""

    name: str
    title: str
    camera: str
    frame: str

    def camera_name(self, channel: str) -> str:
        return self.camera.format(channel=channel, lower=channel.lower())

    def frame_id(self, channel: str) -> str:
        return self.frame.format(channel=channel, lower=channel.lower())

    def camera_names(self) -> list[str]:
        """The node's ``camera_names`` for this layout, in the model's camera order."""
        return [self.camera_name(c) for c in CAMERA_NAMES]


CONVERTERS = {c.name: c for c in (
    Converter("odg", "odg bag (this project)", "{channel}", "{channel}"),
    Converter("foxglove", "nuscenes_to_ros2bag, the ROS 2 port of Foxglove's nuscenes2mcap",
              "{channel}", "{channel}"),
    Converter("chris7462", "Chris7462/nuscenes_to_ros2bag", "{lower}", "{lower}_link"),
    Converter("nuscenes2bag", "clynamen/nuscenes2bag (ROS 1), converted with rosbags-convert",
              "{lower}", "{lower}"),
)}
