"""Each nuScenes converter layout (testing/bag_layouts.py) replayed into odg_node as
docs/bags.md says, across processes with real rclpy: the node started with the layout's params
file (config/bags/), `odg replay BAG --clock` with the layout's options, this process
listening to the grids and /diagnostics. The world has keyframe gaps of 0.55 and 0.75 s.

Checked at the end: grids came out, no input was refused (no pose_miss, no missing
extrinsics or CameraInfo, no bad input of any kind), and every completed camera set was
either published or dropped as stale (the model is slower than the cameras here).
"""
from __future__ import annotations

import subprocess
import sys

import pytest

from odg_ros.bags.converters import CONVERTERS
from odg_ros.bags.reader import bag_topics
from odg_ros.online.errors import BAD_INPUT_KINDS
from odg_ros.resources import resource_path
from testing.node_harness import checkpoint, spin_until, stop  # noqa: F401

NAMESPACE = "/odg_layouts"
NODE = f"{NAMESPACE}/odg_node"

# layout -> (params file, node overrides beyond it, odg replay options, the node's inputs:
# image and CameraInfo topic patterns, other topics)
LAYOUTS = {
    "odg": ("config/odg.yaml", {"use_sim_time": True}, [],
            ("/{camera}/image_rect_compressed", "/{camera}/camera_info", "/tf", "/tf_static")),
    "foxglove": ("config/bags/foxglove.yaml", {},
                 ["--remap", "/diagnostics:=/can/diagnostics"],
                 ("/{camera}/image_rect_compressed", "/{camera}/camera_info", "/tf", "/odom")),
    "foxglove tf": ("config/bags/foxglove_tf.yaml", {},
                    ["--remap", "/diagnostics:=/can/diagnostics"],
                    ("/{camera}/image_rect_compressed", "/{camera}/camera_info", "/tf")),
    "chris7462": ("config/bags/chris7462.yaml", {"rig_file": "chris7462"}, [],
                  ("/nuscenes/{camera}/image_raw", "/nuscenes/{camera}/camera_info",
                   "/nuscenes/odom")),
    "nuscenes2bag": ("config/bags/nuscenes2bag.yaml", {"rig_file": "nuscenes2bag"}, [],
                     ("/{camera}/raw", "/tf")),
}


class Listener:
    """The grids and the node's diagnostics, as a planner would receive them."""

    def __init__(self, rclpy, context):
        from diagnostic_msgs.msg import DiagnosticArray
        from odg_ros_msgs.msg import SemanticVoxelGrid
        from rclpy.executors import SingleThreadedExecutor
        self.node = rclpy.create_node("layout_test_listener", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.grids = []
        self.status = None
        self.node.create_subscription(SemanticVoxelGrid, f"{NODE}/occupancy",
                                      lambda m: self.grids.append(m.header.stamp), 50)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._diagnostics, 50)

    def _diagnostics(self, array):
        for status in array.status:
            if status.name.startswith(NODE):
                self.status = status

    def counters(self) -> dict[str, int]:
        if self.status is None:
            return {}
        return {kv.key: int(kv.value) for kv in self.status.values if kv.value.isdigit()}

    def spin_until(self, predicate, timeout, child=None, log=None) -> bool:
        return spin_until(self.executor, predicate, timeout, child, log)


def settled(listener, replay) -> bool:
    """The replay is over and the last diagnostics account for every completed set."""
    c = listener.counters()
    return replay.poll() is not None and bool(c) and c["sets_completed"] > 0 and \
        c["sets_completed"] == c["outputs"] + c["stale_sets_dropped"] + sum(
            c[k] for k in BAD_INPUT_KINDS)


@pytest.mark.parametrize("layout", ["odg", "foxglove", "foxglove tf", "chris7462",
                                    "nuscenes2bag"])
def test_a_layout_replays_into_the_node(layout, layout_world, checkpoint, ros_context,
                                        rclpy_module, tmp_path):
    params, overrides, replay_options, inputs = LAYOUTS[layout]
    bag = layout_world.bags[layout.split()[0]]
    overrides = dict(overrides, checkpoint=str(checkpoint), device="cpu",
                     diagnostics_period=0.25)
    if "rig_file" in overrides:
        overrides["rig_file"] = str(layout_world.rigs[overrides["rig_file"]])
    command = [sys.executable, "-m", "odg_ros.ros.node", "--ros-args",
               "--params-file", str(resource_path(params)), "-r", f"__ns:={NAMESPACE}"]
    for name, value in overrides.items():
        command += ["-p", f"{name}:={str(value).lower() if isinstance(value, bool) else value}"]
    log_path = tmp_path / "node.log"
    with open(log_path, "w") as log:
        node = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    replay = None
    listener = Listener(rclpy_module, ros_context)
    try:
        cameras = CONVERTERS[layout.split()[0]].camera_names()
        topics = sorted({t.format(camera=c) for t in inputs for c in cameras})
        up = listener.spin_until(
            lambda: all(listener.node.count_subscribers(t) for t in topics)
            and listener.node.count_publishers(f"{NODE}/occupancy"), 120, node, log_path)
        assert up, f"node did not come up:\n{log_path.read_text()}"
        # only the node's inputs, so that the replay can wait until the node hears each of
        # them: the bag lasts two seconds, what goes out before discovery is lost
        recorded = {t.lstrip("/"): t for t in bag_topics(bag)}
        replay = subprocess.Popen([sys.executable, "-m", "odg_ros.commands", "replay",
                                   str(bag), "--clock", "--quiet", *replay_options, "--topics",
                                   *[recorded[t.lstrip("/")] for t in topics],
                                   "--wait-for-subscribers", "60"],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        done = listener.spin_until(lambda: settled(listener, replay), 120, node, log_path)
        out, err = replay.communicate(timeout=30)
        assert replay.returncode == 0, err
        assert done, (listener.counters(), log_path.read_text()[-3000:])
        counters = listener.counters()
        # none: a set completed before its pose, its camera transforms or its first
        # CameraInfo (published next to the image; the executor picks callbacks in its own
        # order) waits for them
        refused = {k: counters[k] for k in BAD_INPUT_KINDS if counters[k]}
        assert not refused, (refused, log_path.read_text()[-3000:])
        assert counters["outputs"] >= 1 and len(listener.grids) >= 1
        # the camera sets the bag holds (best effort DDS may lose a message under load)
        assert counters["sets_completed"] >= len(layout_world.camera_sets_us()) // 2, counters
    finally:
        if replay is not None:
            stop(replay)
        stop(node)
        listener.node.destroy_node()


def test_a_type_rclpy_does_not_know_is_skipped(layout_world, rclpy_module):
    """The Foxglove-derived bag's foxglove_msgs markers: named, the rest plays."""
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "replay",
                             str(layout_world.bags["foxglove"]), "--rate", "20", "--quiet"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "skipped /CAM_FRONT/image_markers_annotations: message type " \
        "foxglove_msgs/msg/ImageMarkerArray is not available to rclpy" in result.stdout
