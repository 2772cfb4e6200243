"""The side of a test that talks to odg_node in its own process over real rclpy: the node
started with a params file (``start_node``), a harness that publishes its inputs and records
its outputs, the ego path the inputs follow, and stopping and waiting on the process."""
from __future__ import annotations

import io
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image as PILImage

from odg_ros.geometry import make_transform
from odg_ros.resources import resource_path
from odg_ros.ros.soak_run import stop_process
from testing.helpers import write_tiny_checkpoint
from testing.online import CAMS, HW, OFFSETS, png, scaled_K, set_images


def stop(child, timeout=15):
    """SIGINT, as ros2 launch stops a node; killed if it has not exited after ``timeout`` s."""
    stop_process(child, timeout)


def spin_until(executor, predicate, timeout, child=None, log=None) -> bool:
    """Spin until ``predicate()`` (True) or ``timeout`` s (False); raises with the node's log
    (an open file or a path) if the node process ``child`` exits meanwhile."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
        if predicate():
            return True
        if child is not None and child.poll() is not None:
            if isinstance(log, (str, Path)):
                text = Path(log).read_text()
            else:
                log.seek(0)
                text = log.read()
            raise AssertionError(f"node exited with {child.returncode}:\n{text}")
    return False


NAMESPACE = "/odg_test"
NODE = f"{NAMESPACE}/odg_node"
SPEED, YAW_RATE = 5.0, 0.1
# fast diagnostics and a short no-output timeout
FAST = dict(diagnostics_period=0.2, no_output_timeout=1.0)


def pose_at(t, t0):
    """Straight line + constant yaw rate: linear/slerp interpolation of it is exact."""
    yaw = YAW_RATE * (t - t0)
    return make_transform([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)],
                          (SPEED * (t - t0), 0.5 * (t - t0), 0.0))


def jpeg(array):
    buffer = io.BytesIO()
    PILImage.fromarray(array).save(buffer, format="JPEG")
    return buffer.getvalue()


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return write_tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt")


def write_params(path, checkpoint, **overrides):
    params = yaml.safe_load(resource_path("config/odg.yaml").read_text())["/**"]["ros__parameters"]
    params.update(checkpoint=str(checkpoint), device="cpu", image_transport="compressed",
                  image_topic="/test/{camera}/image", camera_info_topic="/test/{camera}/info",
                  pose_source="odometry", odometry_topic="/test/odom", output_frame="ego_test",
                  score_threshold=0.0, box_score_threshold=0.0, diagnostics_period=0.2,
                  warn_throttle=0.2, history_max_gap=2.0,
                  # the offline model's arithmetic on every CPU (auto picks by the CPU)
                  precision="fp32")
    params.update(overrides)
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": params}}))
    return params


@pytest.fixture
def start_node(tmp_path):
    children = []

    def start(checkpoint, **overrides):
        params_file = tmp_path / f"params{len(children)}.yaml"
        params = write_params(params_file, checkpoint, **overrides)
        log = open(tmp_path / f"node{len(children)}.log", "w+")
        child = subprocess.Popen(
            [sys.executable, "-m", "odg_ros.ros.node", "--ros-args", "--params-file",
             str(params_file), "-r", f"__ns:={NAMESPACE}"], stdout=log, stderr=subprocess.STDOUT)
        children.append((child, log))
        return child, params, log

    yield start
    for child, log in children:
        stop(child, timeout=10)
        log.close()


class Harness:
    """The test's side: publishers of the node's inputs, recorders of its outputs."""

    def __init__(self, rclpy, context):
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import OccupancyGrid, Odometry
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import CameraInfo, CompressedImage, PointCloud2
        from tf2_msgs.msg import TFMessage
        from visualization_msgs.msg import MarkerArray

        from odg_ros_msgs.msg import DynamicObjectArray, SemanticVoxelGrid
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        self.node = rclpy.create_node("odg_test_harness", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        n = self.node
        self.images = {c: n.create_publisher(CompressedImage, f"/test/{c}/image", 10)
                       for c in CAMS}
        self.infos = {c: n.create_publisher(CameraInfo, f"/test/{c}/info", 10) for c in CAMS}
        self.odom = n.create_publisher(Odometry, "/test/odom", 200)
        self.tf = n.create_publisher(TFMessage, "/tf", 100)
        self.tf_static = n.create_publisher(
            TFMessage, "/tf_static", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                                                durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.received = {name: [] for name in ("grid", "cloud", "bev", "objects", "markers",
                                               "diagnostics")}
        for name, cls, topic in [("grid", SemanticVoxelGrid, f"{NODE}/occupancy"),
                                 ("cloud", PointCloud2, f"{NODE}/occupancy/cloud"),
                                 ("bev", OccupancyGrid, f"{NODE}/occupancy/bev"),
                                 ("objects", DynamicObjectArray, f"{NODE}/objects"),
                                 ("markers", MarkerArray, f"{NODE}/objects/markers"),
                                 ("diagnostics", DiagnosticArray, "/diagnostics")]:
            n.create_subscription(cls, topic, lambda m, k=name: self.received[k].append(m), 50)
        self.classes = dict(CompressedImage=CompressedImage, CameraInfo=CameraInfo,
                            Odometry=Odometry, TFMessage=TFMessage)

    def spin_until(self, predicate, timeout, child=None, log=None):
        return spin_until(self.executor, predicate, timeout, child, log)

    def wait_for_node(self, child, log, timeout=90.0):
        ok = self.spin_until(
            # the camera infos too: one published before its subscription matched is lost
            lambda: all(p.get_subscription_count() > 0
                        for p in (*self.images.values(), *self.infos.values()))
            and self.node.count_publishers(f"{NODE}/occupancy") > 0
            and self.node.count_publishers("/diagnostics") > 0, timeout, child, log)
        if not ok:
            log.seek(0)
            raise AssertionError(f"node did not come up:\n{log.read()}")

    def stamp(self, t):
        from builtin_interfaces.msg import Time
        sec = int(np.floor(t))
        return Time(sec=sec, nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)

    def publish_infos(self, K_of=scaled_K, hw=HW):
        for c in CAMS:
            msg = self.classes["CameraInfo"]()
            msg.header.frame_id = c
            msg.height, msg.width = hw
            msg.k = [float(v) for v in np.asarray(K_of(c)).ravel()]
            self.infos[c].publish(msg)

    def publish_pose(self, t, T, quaternion_wxyz=None):
        from odg_ros.geometry import matrix_to_quaternion
        msg = self.classes["Odometry"]()
        msg.header.stamp = self.stamp(t)
        msg.header.frame_id, msg.child_frame_id = "map", "base_link"
        w, x, y, z = (matrix_to_quaternion(T[:3, :3]) if quaternion_wxyz is None
                      else quaternion_wxyz)
        msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = T[:3, 3]
        o = msg.pose.pose.orientation
        o.w, o.x, o.y, o.z = w, x, y, z
        self.odom.publish(msg)

    def publish_poses(self, t_from, t_to, t0, rate=20.0):
        # paced: the node subscribes best-effort (depth 100), a burst could overflow it
        for t in np.arange(t_from, t_to, 1.0 / rate):
            self.publish_pose(float(t), pose_at(float(t), t0))
            time.sleep(0.003)

    def publish_set(self, start, images, encode=png, fmt="png"):
        for c, offset, image in zip(CAMS, OFFSETS, images):
            msg = self.classes["CompressedImage"]()
            msg.header.stamp = self.stamp(start + offset)
            msg.header.frame_id = c
            msg.format = fmt
            msg.data = encode(image)
            self.images[c].publish(msg)

    def feed_until(self, predicate, t0, child, log, timeout=60.0):
        """Camera infos, poses and a new set every 2 s until ``predicate``: the node reads
        them best effort (sensor QoS), and what is sent before its readers have matched ours
        is lost, which a loaded machine shows; each set is newer than the last."""
        deadline = time.monotonic() + timeout
        start = t0 + 0.2
        while time.monotonic() < deadline:
            self.publish_infos()
            self.publish_poses(start - 0.7, start + 0.8, t0)
            self.publish_set(start, set_images(0))
            if self.spin_until(predicate, 2.0, child, log):
                return True
            start += 0.5
        return False

    def counters(self):
        """The latest diagnostics counters of the node."""
        for array in reversed(self.received["diagnostics"]):
            for status in array.status:
                if "odg_node" in status.name:
                    return {kv.key: kv.value for kv in status.values}, status
        return {}, None

    def get_parameters(self, names):
        from rcl_interfaces.srv import GetParameters
        client = self.node.create_client(GetParameters, f"{NODE}/get_parameters")
        assert self.spin_until(lambda: client.service_is_ready(), 30)
        # Fast DDS drops a response whose reader it has not matched within 100 ms ("failed to
        # send response (timeout)" in the node's log), which a loaded machine can exceed even
        # after service_is_ready(); the request is read-only, so sending it again is safe.
        for _ in range(3):
            future = client.call_async(GetParameters.Request(names=names))
            if self.spin_until(future.done, 15):
                break
        assert future.done(), "no get_parameters response in three tries"
        from rclpy.parameter import parameter_value_to_python
        return {n: parameter_value_to_python(v) for n, v in zip(names, future.result().values)}


def tf_transform(h, parent, child_frame, t, T):
    from geometry_msgs.msg import TransformStamped

    from odg_ros.geometry import matrix_to_quaternion
    msg = TransformStamped()
    msg.header.stamp = h.stamp(t)
    msg.header.frame_id, msg.child_frame_id = parent, child_frame
    w, x, y, z = matrix_to_quaternion(T[:3, :3])
    msg.transform.translation.x, msg.transform.translation.y, \
        msg.transform.translation.z = T[:3, 3]
    r = msg.transform.rotation
    r.w, r.x, r.y, r.z = w, x, y, z
    return msg
