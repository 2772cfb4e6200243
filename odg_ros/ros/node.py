"""odg_node: the ODG occupancy network as a ROS 2 node (wiring only).

Everything that decides anything lives in the ROS-free pipeline (odg_ros/online/); this
module declares the parameters, converts messages to and from plain values, decodes each
set in one thread and runs the model in another (the next set decodes while the model runs;
latest-wins mailboxes between them), and publishes.

Inputs (all remappable): one image topic per camera (CompressedImage or Image, best-effort
sensor QoS), one CameraInfo per camera, the ego pose from /tf (+ /tf_static) or an Odometry
topic, camera extrinsics from a rig file or TF. TF is read straight from tf2_msgs/TFMessage
into a small transform buffer (online/transforms.py), so the node does not need tf2_ros.

Outputs (reliable, keep-last 1): ~/occupancy (odg_ros_msgs/SemanticVoxelGrid),
~/occupancy/cloud (PointCloud2: occupied voxel centres, x y z float32 + label uint8),
~/occupancy/bev (OccupancyGrid: 100 where a column holds anything but free or
driveable_surface between bev_min_z and bev_max_z), ~/objects (odg_ros_msgs/
DynamicObjectArray), ~/objects/markers (MarkerArray), ~/fps (Float32), /diagnostics.
Every output is in ``output_frame`` (the ego at the reference camera's stamp), stamped with
that camera's header stamp.

Bad input (corrupt image, wrong size or encoding, missing CameraInfo, NaN / non-orthonormal
pose, pose miss, future stamp) never stops the node: a warning throttled per kind, a
diagnostics counter, and the set is skipped.

    odg_node --ros-args --params-file config/odg.yaml
"""
from __future__ import annotations

import array
import signal
import sys
import threading
import time
import traceback

import numpy as np
import rclpy
from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, Quaternion, Vector3
from nav_msgs.msg import OccupancyGrid, Odometry
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Float32, Header
from visualization_msgs.msg import Marker, MarkerArray

from odg_ros_msgs.msg import DynamicObject, DynamicObjectArray, SemanticVoxelGrid

from ..network.checkpoint import load_model
from ..network.precision import resolve_device, slow_precision_warning
from ..online import packing
from ..online.diagnostics import PipelineStats
from ..online import parameters as node_parameters
from ..online.errors import BadInput
from ..online.images import EncodedImage
from ..online.pipeline import OnlinePipeline, PipelineSettings
from ..online.poses import pose_from_xyz_xyzw
from ..online.predictor import OnlinePredictor
from ..online.rig import IntrinsicsRange, load_rig
from ..online.sync import stamp_to_seconds
from ..online.transforms import TransformBuffer
from ..resources import resource_path, shipped_checkpoint

NODE_NAME = "odg_node"

# The parameters' types, defaults, ranges and descriptions: config/odg_node.schema.yaml.
_PARAMETER_TYPES = {"bool": ParameterType.PARAMETER_BOOL,
                    "int": ParameterType.PARAMETER_INTEGER,
                    "float": ParameterType.PARAMETER_DOUBLE,
                    "string": ParameterType.PARAMETER_STRING,
                    "string_array": ParameterType.PARAMETER_STRING_ARRAY}

OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
TF_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                    reliability=ReliabilityPolicy.RELIABLE)
TF_STATIC_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)


def stamp_seconds(stamp) -> float:
    """Raises BadInput('bad_stamp') for a stamp that is no valid time."""
    return stamp_to_seconds(stamp.sec, stamp.nanosec)


def _u8(data) -> array.array:
    """A uint8[] field value from bytes or a uint8 array (one memcpy)."""
    out = array.array("B")
    out.frombytes(data)
    return out


def _refilled_u8(field: array.array, values: np.ndarray) -> array.array:
    """``field`` holding ``values`` (flat uint8): overwritten in place when the size is the
    same, so a grid a set costs one memcpy and no allocation."""
    if len(field) != values.size:
        return _u8(values)
    np.frombuffer(field, np.uint8)[:] = values
    return field


class ReusedMessages:
    """The grid and object messages, refilled for each result instead of built anew: rclpy
    serialises a message inside publish(), so it is free again once publish returns, and
    building ~250 nested message objects a set (30 boxes) cost more than the rest of publish."""

    def __init__(self):
        self.grid = SemanticVoxelGrid()
        self.objects: list[DynamicObject] = []

    def grid_message(self, header: Header, fields: dict) -> SemanticVoxelGrid:
        grid = self.grid
        grid.header = header
        grid.origin = _pose_msg(fields["origin_position"])
        grid.resolution = fields["resolution"]
        grid.size_x, grid.size_y, grid.size_z = \
            fields["size_x"], fields["size_y"], fields["size_z"]
        grid.memory_order = fields["memory_order"]
        grid.free_label, grid.unknown_label = fields["free_label"], fields["unknown_label"]
        grid.class_names = fields["class_names"]
        grid.labels = _refilled_u8(grid.labels, fields["labels"])
        grid.confidence = _refilled_u8(grid.confidence, fields["confidence"])
        return grid

    def object_array(self, header: Header, boxes: list[dict]) -> DynamicObjectArray:
        while len(self.objects) < len(boxes):
            self.objects.append(DynamicObject())
        for box, obj in zip(boxes, self.objects):
            o = packing.object_fields(box)
            obj.class_id, obj.class_name, obj.score = o["class_id"], o["class_name"], o["score"]
            position, orientation = obj.pose.position, obj.pose.orientation
            position.x, position.y, position.z = o["position"]
            orientation.w, orientation.x, orientation.y, orientation.z = o["orientation"]
            obj.size.x, obj.size.y, obj.size.z = o["size"]
            linear = obj.velocity.linear
            linear.x, linear.y, linear.z = o["velocity"]
        return DynamicObjectArray(header=header, objects=self.objects[:len(boxes)])


def _pose_msg(position, orientation_wxyz=(1.0, 0.0, 0.0, 0.0)) -> Pose:
    w, x, y, z = orientation_wxyz
    return Pose(position=Point(x=float(position[0]), y=float(position[1]),
                               z=float(position[2])),
                orientation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)))


class OdgNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        # set first: rclpy destroys a node whose constructor failed when it shuts down
        self._stop = threading.Event()
        self._worker = None
        self.pipeline = None
        schema = node_parameters.load_schema()
        for name, parameter in schema.items():
            # read_only: every parameter is read once at start-up; a later change is refused
            # instead of being silently ignored.
            # a float parameter also takes an integer (slop: 1 in a YAML file); the schema
            # check below converts it
            descriptor = ParameterDescriptor(description=parameter.description,
                                             type=_PARAMETER_TYPES[parameter.type],
                                             additional_constraints=parameter.constraint(),
                                             read_only=True,
                                             dynamic_typing=parameter.type == "float")
            self.declare_parameter(name, parameter.default, descriptor)
        p = node_parameters.validate({name: self.get_parameter(name).value for name in schema},
                                     schema)
        self.params = p
        self.base_frame = p["base_frame"]
        self.output_frame = p["output_frame"] or p["base_frame"]
        cameras = list(p["camera_names"])

        # --- model ---------------------------------------------------------------------
        device = resolve_device(p["device"])
        thresholds = {k: float(p[k]) for k in ("score_threshold", "box_score_threshold")
                      if float(p[k]) >= 0}
        if not p["checkpoint"].strip():
            raise ValueError("checkpoint is empty: give a path, shipped (the packaged "
                             "model/odg_cpu.pt) or random (random weights, for tests)")
        if p["checkpoint"] == "random":
            model, cfg = load_model(None, p["preset"], device, **thresholds)
            self.get_logger().warning(
                f"checkpoint random: preset {p['preset']} with RANDOM WEIGHTS on {device}. "
                "The published occupancy and objects are meaningless.")
        else:
            path = shipped_checkpoint() if p["checkpoint"] == "shipped" else p["checkpoint"]
            model, cfg = load_model(path, device=device, **thresholds)
            self.get_logger().info(f"loaded {path} ({cfg.name}) on {device}, "
                                   f"precision {p['precision']}")
        slow = slow_precision_warning(p["precision"], device)
        if slow:
            self.get_logger().warning(slow)
        self.cfg = cfg
        history = int(p["history_frames"]) or None
        predictor = OnlinePredictor(model, cfg, device, max_gap=float(p["history_max_gap"]),
                                    num_frames=history,
                                    min_interval=float(p["history_interval"]),
                                    precision=p["precision"], compile=p["compile"],
                                    compiled_step=p["compiled_step"].strip() or None)
        self.get_logger().info(f"online step: {predictor.mode} mode, start-up (compile, "
                               f"capture) {predictor.startup_seconds:.1f} s")

        # --- poses and extrinsics ---------------------------------------------------------
        self.tf = TransformBuffer(max_extrapolation=float(p["max_pose_extrapolation"]),
                                  cache_time=float(p["tf_cache_time"]),
                                  max_speed=float(p["max_speed"]),
                                  max_acceleration=float(p["max_acceleration"]))
        # /tf frames looked up from: the ego frame, and each camera's CameraInfo frame
        self._tf_base = {p["base_frame"]} if p["pose_source"] == "tf" else set()
        self._tf_cameras: dict[str, str] = {}
        self.tf.set_wanted(self._tf_base)
        pose_lookup = None
        if p["pose_source"] == "tf":
            global_frame, base = p["global_frame"], p["base_frame"]
            pose_lookup = lambda t: self.tf.lookup(global_frame, base, t, "pose_miss")  # noqa
        if p["extrinsics_source"] == "rig":
            rig = load_rig(p["rig_file"] or resource_path("config/rig_nuscenes.yaml"))
            missing = [c for c in cameras if c not in rig.cameras]
            if missing:
                raise ValueError(f"cameras {missing} are not in the rig file "
                                 f"(it has {list(rig.cameras)})")
            extrinsics = lambda camera, frame_id, t: rig.cameras[camera].sensor2ego  # noqa
        else:
            base = p["base_frame"]
            extrinsics = lambda camera, frame_id, t: self.tf.lookup(  # noqa
                base, frame_id, t, "missing_extrinsics")

        self.stats = PipelineStats(stale_after_s=float(p["no_output_timeout"]),
                                   max_tf_rate=float(p["max_tf_rate"]))
        self.internal_errors = 0
        self._error_lock = threading.Lock()
        self.pipeline = OnlinePipeline(
            predictor,
            PipelineSettings(cameras, slop=float(p["slop"]),
                             max_future=float(p["max_future_stamp"]),
                             pose_max_extrapolation=float(p["max_pose_extrapolation"]),
                             intrinsics=IntrinsicsRange(
                                 float(p["min_focal_length"]), float(p["max_focal_length"]),
                                 float(p["max_principal_point_offset"])),
                             max_speed=float(p["max_speed"]),
                             max_acceleration=float(p["max_acceleration"]),
                             max_image_pixels=int(p["max_image_pixels"])),
            extrinsics, pose_lookup, self.stats)
        self._bad_input_loggers = {}

        # --- publishers -----------------------------------------------------------------
        self.messages = ReusedMessages()
        self.pub_grid = self.create_publisher(SemanticVoxelGrid, "~/occupancy", OUTPUT_QOS)
        self.pub_cloud = self.create_publisher(PointCloud2, "~/occupancy/cloud", OUTPUT_QOS)
        self.pub_bev = self.create_publisher(OccupancyGrid, "~/occupancy/bev", OUTPUT_QOS)
        self.pub_objects = self.create_publisher(DynamicObjectArray, "~/objects", OUTPUT_QOS)
        self.pub_markers = self.create_publisher(MarkerArray, "~/objects/markers", OUTPUT_QOS)
        self.pub_fps = self.create_publisher(Float32, "~/fps", OUTPUT_QOS)
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)

        # --- subscriptions --------------------------------------------------------------
        image_type = CompressedImage if p["image_transport"] == "compressed" else Image
        self._inputs = []
        for camera in cameras:
            image_topic = p["image_topic"].format(camera=camera)
            info_topic = p["camera_info_topic"].format(camera=camera)
            self._inputs.append(self.create_subscription(
                image_type, image_topic, lambda m, c=camera: self.on_image(c, m),
                qos_profile_sensor_data))
            self._inputs.append(self.create_subscription(
                CameraInfo, info_topic, lambda m, c=camera: self.on_camera_info(c, m),
                qos_profile_sensor_data))
        if p["pose_source"] == "odometry":
            self._inputs.append(self.create_subscription(
                Odometry, p["odometry_topic"], self.on_odometry,
                QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)))
        if p["pose_source"] == "tf" or p["extrinsics_source"] == "tf":
            from tf2_msgs.msg import TFMessage    # on ROS installs and in the venv shim
            self._inputs.append(self.create_subscription(
                TFMessage, "/tf", lambda m: self.on_tf(m, False), TF_QOS))
            self._inputs.append(self.create_subscription(
                TFMessage, "/tf_static", lambda m: self.on_tf(m, True), TF_STATIC_QOS))

        self.create_timer(float(p["diagnostics_period"]), self.publish_diagnostics)
        # decoding runs ahead of the model: set n+1 decodes while the model runs on set n
        self.get_logger().info(self.pipeline.jpeg_decoder_reason)
        self.pipeline.start_decoding(self.warn_bad_input, self._internal_error)
        self._worker = threading.Thread(target=self._work, name="odg_inference", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"{cfg.name}: {len(cameras)} cameras ({p['image_transport']}), pose from "
            f"{p['pose_source']}, extrinsics from {p['extrinsics_source']}, history "
            f"{predictor.history.capacity} frames, outputs in {self.output_frame}")

    # ------------------------------------------------------------------ bad input reporting
    def warn_bad_input(self, error: BadInput) -> None:
        logger = self._bad_input_loggers.get(error.kind)
        if logger is None:       # one logger per kind: each kind is throttled on its own
            logger = self._bad_input_loggers[error.kind] = \
                self.get_logger().get_child(error.kind)
        logger.warning(f"skipped: {error.message}",
                       throttle_duration_sec=float(self.params["warn_throttle"]))

    def now_seconds(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    # ------------------------------------------------------------------------- callbacks
    def on_image(self, camera: str, msg) -> None:
        if isinstance(msg, CompressedImage):
            image = EncodedImage(True, msg.format, bytes(msg.data))
        else:
            image = EncodedImage(False, msg.encoding, bytes(msg.data), msg.height, msg.width,
                                 msg.step)
        try:
            stamp = self._checked_stamp(msg.header.stamp)
            self.pipeline.on_image(camera, stamp, image, self.now_seconds(),
                                   header=msg.header.stamp)
        except BadInput as error:
            self.warn_bad_input(error)

    def _checked_stamp(self, stamp) -> float:
        try:
            return stamp_seconds(stamp)
        except BadInput as error:
            raise self.pipeline.count_bad_input(error) from None

    def on_camera_info(self, camera: str, msg: CameraInfo) -> None:
        try:
            self._checked_stamp(msg.header.stamp)
            self.pipeline.on_camera_info(camera, np.asarray(msg.k), msg.height, msg.width,
                                         msg.header.frame_id)
        except BadInput as error:
            self.warn_bad_input(error)
            return
        if self.params["extrinsics_source"] == "tf" and \
                self._tf_cameras.get(camera) != msg.header.frame_id:
            self._tf_cameras[camera] = msg.header.frame_id
            self.tf.set_wanted(self._tf_base | set(self._tf_cameras.values()))

    def on_odometry(self, msg: Odometry) -> None:
        position, orientation = msg.pose.pose.position, msg.pose.pose.orientation
        try:
            stamp = stamp_seconds(msg.header.stamp)
            T = pose_from_xyz_xyzw((position.x, position.y, position.z),
                                   (orientation.x, orientation.y, orientation.z, orientation.w))
        except BadInput as error:
            self.warn_bad_input(self.pipeline.count_bad_input(error))
            return
        try:
            self.pipeline.on_pose(stamp, T)
        except BadInput as error:     # counted by the pipeline
            self.warn_bad_input(error)

    def on_tf(self, msg, static: bool) -> None:
        wants = self.tf.wants
        for transform in msg.transforms:
            # A busy tree: most dynamic transforms are off the chains we look up; drop them
            # by name before converting anything (statics are few and kept, up to a cap).
            if not static and not wants(transform.child_frame_id):
                continue
            t, r = transform.transform.translation, transform.transform.rotation
            try:
                stamp = stamp_seconds(transform.header.stamp)
                T = pose_from_xyz_xyzw((t.x, t.y, t.z), (r.x, r.y, r.z, r.w))
                self.tf.add(transform.header.frame_id, transform.child_frame_id, stamp, T,
                            static)
            except BadInput as error:
                self.warn_bad_input(self.pipeline.count_bad_input(error))

    # ------------------------------------------------------------------------ inference
    def _work(self) -> None:
        while not self._stop.is_set():
            prepared = self.pipeline.next_prepared(timeout=0.2)
            if prepared is None:
                continue
            try:
                self.publish(self.pipeline.infer(prepared))
            except BadInput as error:
                self.warn_bad_input(error)
            except Exception:     # never let the worker die silently: log, count, go on
                self._internal_error()

    def _internal_error(self) -> None:
        """Inside an ``except`` block of the decoding or the inference thread."""
        with self._error_lock:
            self.internal_errors += 1
        self.get_logger().error(f"{threading.current_thread().name} failed:\n"
                                f"{traceback.format_exc()}",
                                throttle_duration_sec=5.0)

    def publish(self, result) -> None:
        start = time.perf_counter()
        header = Header(stamp=result.header if isinstance(result.header, TimeMsg)
                        else TimeMsg(), frame_id=self.output_frame)
        cfg = self.cfg
        fields = packing.voxel_grid_fields(result.grid, result.confidence, cfg.pc_range,
                                           cfg.voxel_size, cfg.labels)
        grid = self.messages.grid_message(header, fields)
        self.pub_grid.publish(grid)

        if self.pub_cloud.get_subscription_count():
            c = packing.cloud_fields(result.grid, cfg.pc_range, cfg.voxel_size, cfg.labels)
            cloud = PointCloud2(header=header, height=c["height"], width=c["width"],
                                fields=[PointField(name=n, offset=o, datatype=d, count=k)
                                        for n, o, d, k in c["fields"]],
                                is_bigendian=c["is_bigendian"], point_step=c["point_step"],
                                row_step=c["row_step"], is_dense=c["is_dense"])
            cloud.data = _u8(c["data"])
            self.pub_cloud.publish(cloud)

        if self.pub_bev.get_subscription_count():
            b = packing.bev_fields(result.grid, cfg.pc_range, cfg.voxel_size,
                                   float(self.params["bev_min_z"]),
                                   float(self.params["bev_max_z"]), cfg.labels)
            bev = OccupancyGrid(header=header)
            bev.info.map_load_time = header.stamp
            bev.info.resolution = b["resolution"]
            bev.info.width, bev.info.height = b["width"], b["height"]
            bev.info.origin = _pose_msg(b["origin_position"])
            bev.data = array.array("b", b["data"])
            self.pub_bev.publish(bev)

        objects = self.messages.object_array(header, result.boxes)
        self.pub_objects.publish(objects)

        if self.pub_markers.get_subscription_count():
            markers = MarkerArray(markers=[Marker(header=header, action=Marker.DELETEALL)])
            for i, obj in enumerate(objects.objects):
                r, g, b = packing.box_color(obj.class_id)
                markers.markers.append(Marker(
                    header=header, ns="objects", id=i, type=Marker.CUBE, action=Marker.ADD,
                    pose=obj.pose, scale=Vector3(x=obj.size.x, y=obj.size.y, z=obj.size.z),
                    color=ColorRGBA(r=r, g=g, b=b, a=0.5)))
                markers.markers.append(Marker(
                    header=header, ns="labels", id=i, type=Marker.TEXT_VIEW_FACING,
                    action=Marker.ADD, pose=_pose_msg((obj.pose.position.x,
                                                       obj.pose.position.y,
                                                       obj.pose.position.z + obj.size.z)),
                    scale=Vector3(z=0.8), color=ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0),
                    text=f"{obj.class_name} {obj.score:.2f}"))
            self.pub_markers.publish(markers)

        timings = dict(result.timings)
        timings["publish"] = time.perf_counter() - start
        self.stats.record_output(result.stamp, self.now_seconds(), timings)

    # ----------------------------------------------------------------------- diagnostics
    def counters(self) -> dict[str, int]:
        counters = self.pipeline.counters()
        tf_counters = dict(self.tf.counters)
        tf_counters["pose_teleports"] += counters.pop("pose_teleports")
        counters.update(tf_counters)
        counters["internal_errors"] = self.internal_errors
        return counters

    def publish_diagnostics(self) -> None:
        status = self.stats.status(self.counters())
        if self.internal_errors:
            status["level"] = max(status["level"], 2)      # DiagnosticStatus.ERROR
            status["message"] += f"; {self.internal_errors} internal errors (see the log)"
        message = DiagnosticStatus(
            level=bytes([status["level"]]), name=f"{self.get_fully_qualified_name()}: pipeline",
            message=status["message"], hardware_id=str(self.pipeline.predictor.device),
            values=[KeyValue(key=k, value=v) for k, v in status["values"]])
        self.pub_diagnostics.publish(DiagnosticArray(
            header=Header(stamp=self.get_clock().now().to_msg()), status=[message]))
        self.pub_fps.publish(Float32(data=float(self.stats.rate_hz())))

    def destroy_node(self):
        self._stop.set()
        if self.pipeline is not None:
            self.pipeline.close()
        if self._worker is not None and self._worker.is_alive():
            self._worker.join(timeout=5.0)
        return super().destroy_node()


def wants_help(argv: list[str]) -> bool:
    """-h / --help among the node's own arguments (those before --ros-args)."""
    own = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    return "-h" in own or "--help" in own


def main(args=None) -> int:
    argv = list(sys.argv if args is None else args)
    if wants_help(argv):
        print(node_parameters.help_text())
        return 0
    # SIGINT/SIGTERM only set a flag checked between executor steps: an asynchronous
    # KeyboardInterrupt can land inside rclpy's Task construction and leave a half-built task
    # that errors when collected (seen at the end of the demo).
    stop = threading.Event()
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node = executor = None
    try:
        try:
            node = OdgNode()
        except (ValueError, OSError, ParameterException) as error:
            # configuration errors (bad parameter, missing / corrupt / incompatible checkpoint,
            # missing rig file): one FATAL line, no traceback
            rclpy.logging.get_logger(NODE_NAME).fatal(f"cannot start: {error}")
            return 1
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while rclpy.ok() and not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        # Shut down cleanly already: more signals change nothing. Ignore them rather than
        # leave our handlers, which Python resets to the default (death by the signal) for
        # its own teardown, where a supervisor's SIGTERM would land.
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
