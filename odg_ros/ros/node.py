"""odg_node: the ODG occupancy network as a ROS 2 node (wiring only).

Everything that decides anything lives in the ROS-free pipeline (odg_ros/online/); this
module declares the parameters, converts messages to and from plain values, decodes each
set in one thread and runs the model in another (the next set decodes while the model runs;
latest-wins mailboxes between them), and publishes.

Inputs (all remappable): one image topic per camera (CompressedImage or Image, best-effort
sensor QoS), one CameraInfo per camera, the ego pose from /tf (+ /tf_static) or an Odometry
topic, camera extrinsics from TF when the data carries them, else a rig file
(online/extrinsics.py). TF is read straight from tf2_msgs/TFMessage into a small transform
buffer (online/transforms.py), so the node does not need tf2_ros. A set whose poses or
transforms have not arrived yet waits for them up to ``pose_wait`` (online/waiting.py).

Outputs (reliable, keep-last 1): ~/occupancy (odg_ros_msgs/SemanticVoxelGrid, with the
observed mask of network/visibility.py), ~/occupancy/cloud (PointCloud2: occupied voxel
centres, x y z float32 + label uint8 + observed uint8), ~/occupancy/bev (OccupancyGrid: 100
where a column holds anything but free or driveable_surface between bev_min_z and
bev_max_z, -1 where it is not seen, else 0), ~/objects (odg_ros_msgs/DynamicObjectArray),
~/objects/markers (MarkerArray), ~/debug/processing_time_ms and
~/debug/pipeline_latency_ms (Float64), ~/fps (Float32), /diagnostics. Every output is in
``output_frame`` (the ego at the reference camera's stamp), stamped with that camera's
header stamp. Diagnostics and ~/fps run on a steady timer (they go on when a replayed bag
and its /clock stop).

Bad input (corrupt image, wrong size or encoding, missing CameraInfo, NaN / non-orthonormal
pose, pose miss, future stamp) never stops the node: a warning throttled per kind, a
diagnostics counter, and the set is skipped.

    odg_node --ros-args --params-file config/odg.yaml
"""
from __future__ import annotations

import re
import signal
import sys
import threading
import time
import traceback
from pathlib import Path

import numpy as np
import rclpy
import rclpy.logging
import torch
import yaml
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.exceptions import ParameterException
from rclpy._rclpy_pybind11 import RCLError
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Float32

from ..network.checkpoint import load_model
from ..network.precision import resolve_device, slow_precision_warning
from ..online.diagnostics import InputMonitor, PipelineStats, transform_topics_needed
from ..online import node_setup, parameters as node_parameters
from ..online.errors import BadInput
from ..online.images import EncodedImage
from ..online.poses import pose_from_xyz_xyzw
from ..online.predictor import OnlinePredictor
from ..online.sync import stamp_to_seconds
from ..resources import shipped_checkpoint
from . import output_messages

NODE_NAME = "odg_node"

# The parameters' types, defaults, ranges and descriptions: config/odg_node.schema.yaml.
_PARAMETER_TYPES = {"bool": ParameterType.PARAMETER_BOOL,
                    "int": ParameterType.PARAMETER_INTEGER,
                    "float": ParameterType.PARAMETER_DOUBLE,
                    "string": ParameterType.PARAMETER_STRING,
                    "string_array": ParameterType.PARAMETER_STRING_ARRAY}

OUTPUT_QOS = output_messages.OUTPUT_QOS
TF_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                    reliability=ReliabilityPolicy.RELIABLE)
TF_STATIC_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)


def stamp_seconds(stamp) -> float:
    """Raises BadInput('bad_stamp') for a stamp that is no valid time."""
    return stamp_to_seconds(stamp.sec, stamp.nanosec)


def encoded_image(msg) -> EncodedImage:
    """A CompressedImage or Image message as the pipeline's EncodedImage (not decoded)."""
    if isinstance(msg, CompressedImage):
        return EncodedImage(True, msg.format, bytes(msg.data))
    return EncodedImage(False, msg.encoding, bytes(msg.data), msg.height, msg.width, msg.step)


class OdgNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        # set first: rclpy destroys a node whose constructor failed when it shuts down
        self._stop = threading.Event()
        self._worker = None
        self.pipeline = None
        p = self.params = self._declare_parameters()
        self.base_frame = p["base_frame"]
        self.output_frame = p["output_frame"] or p["base_frame"]
        cameras = list(p["camera_names"])
        # before the model: a rig file that cannot serve stops the node at once
        found = node_setup.sources(p, cameras, self._log_note)
        predictor = load_predictor(p, self.get_logger())
        self.cfg = predictor.cfg
        self.cameras = cameras
        self.tf, self.extrinsics = found.tf, found.extrinsics
        # /tf frames looked up from: the ego frame, and each camera's frame (from its
        # CameraInfo, or from the rig file with intrinsics_source rig)
        self._tf_base = {p["base_frame"]} if p["pose_source"] == "tf" else set()
        self._tf_cameras: dict[str, str] = {}
        self.tf.set_wanted(self._tf_base | (found.camera_frames()
                                            if p["extrinsics_source"] != "rig" else set()))
        if p["extrinsics_source"] != "rig":
            # a converter sends base_link -> every sensor with the first /tf, maybe before
            # the CameraInfo that names a camera's frame: keep them from the start
            self.tf.keep_children_of({p["base_frame"]})
        self.inputs = InputMonitor()
        self.stats = PipelineStats(stale_after_s=float(p["no_output_timeout"]),
                                   max_tf_rate=float(p["max_tf_rate"]), inputs=self.inputs,
                                   first_set_grace_s=float(p["pose_wait"]))
        self.internal_errors = 0
        self._error_lock = threading.Lock()
        # the wait for poses runs on the node's clock: bag time under use_sim_time
        self.pipeline = node_setup.build_pipeline(predictor, p, cameras, found, self.stats,
                                                  clock=self.now_seconds)
        self._bad_input_loggers = {}
        self.outputs = output_messages.Outputs(self, self.cfg, self.output_frame,
                                        (float(p["bev_min_z"]), float(p["bev_max_z"])))
        self._subscribe(p, cameras)

        # steady: diagnostics go on (and say "no input") when a bag and its /clock stop
        self.create_timer(float(p["diagnostics_period"]), self.publish_diagnostics,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        # decoding runs ahead of the model: set n+1 decodes while the model runs on set n
        self.get_logger().info(self.pipeline.jpeg_decoder_reason)
        self.pipeline.start_decoding(self.warn_bad_input, self._internal_error)
        self._worker = threading.Thread(target=self._work, name="odg_inference", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"{self.cfg.name}: {len(cameras)} cameras ({p['image_transport']}), pose from "
            f"{p['pose_source']}, extrinsics from {p['extrinsics_source']}, intrinsics from "
            f"{p['intrinsics_source'].replace('_', ' ')}, history "
            f"{predictor.history.capacity} frames, outputs in {self.output_frame}")

    # ------------------------------------------------------------------------ start-up
    def _declare_parameters(self) -> dict:
        """Every schema parameter declared (read-only) -> the validated values."""
        schema = node_parameters.load_schema()
        for name, parameter in schema.items():
            # read_only: every parameter is read once at start-up; a later change is refused
            # instead of being silently ignored.
            # a float parameter also takes an integer (slop: 1 in a YAML file), a fraction one
            # a number (query_budget: 0.6); the schema check below converts and checks it
            descriptor = ParameterDescriptor(description=parameter.description,
                                             type=_PARAMETER_TYPES[parameter.type],
                                             additional_constraints=parameter.constraint(),
                                             read_only=True,
                                             dynamic_typing=parameter.type == "float"
                                             or parameter.or_fraction)
            self.declare_parameter(name, parameter.default, descriptor)
        values = node_parameters.validate(
            {name: self.get_parameter(name).value for name in schema}, schema)
        self._refuse_unknown_parameters(schema, values["unknown_parameters"])
        return values

    def _refuse_unknown_parameters(self, schema, mode: str) -> None:
        """Parameters given (params file, -p, launch) that the node does not declare (rclpy
        keeps them in the node's overrides): error raises (one FATAL line), warn warns."""
        text = node_parameters.unknown_parameters_text(
            [name for name in self._parameter_overrides if not self.has_parameter(name)],
            schema)
        if text and mode == "error":
            raise ValueError(f"{text} (unknown_parameters: warn only warns)")
        if text:
            self.get_logger().warning(text)

    def _subscribe(self, p: dict, cameras: list[str]) -> None:
        image_type = CompressedImage if p["image_transport"] == "compressed" else Image
        self._inputs = []
        for camera in cameras:
            self._input(image_type, p["image_topic"].format(camera=camera),
                        lambda m, c=camera: self.on_image(c, m), qos_profile_sensor_data)
            if p["intrinsics_source"] == "camera_info":
                self._input(CameraInfo, p["camera_info_topic"].format(camera=camera),
                            lambda m, c=camera: self.on_camera_info(c, m),
                            qos_profile_sensor_data)
        if p["pose_source"] == "odometry":
            self._input(Odometry, p["odometry_topic"], self.on_odometry,
                        QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
        if p["pose_source"] == "tf" or p["extrinsics_source"] != "rig":
            from tf2_msgs.msg import TFMessage    # on ROS installs and in the venv shim
            tf_needed, either_needed = transform_topics_needed(p["pose_source"],
                                                               p["extrinsics_source"])
            tf = self._input(TFMessage, "/tf", lambda m: self.on_tf(m, False), TF_QOS,
                             needed=tf_needed)
            tf_static = self._input(TFMessage, "/tf_static", lambda m: self.on_tf(m, True),
                                    TF_STATIC_QOS, needed=False)
            if either_needed:
                self.inputs.need_one_of((tf, tf_static))

    def _input(self, message_type, topic: str, callback, qos, needed: bool = True) -> str:
        """A subscription whose messages are counted per topic (its name after remapping)
        for the diagnostics before ``callback`` sees them; returns that name."""
        name = self.resolve_topic_name(topic)
        self.inputs.watch(name, needed)

        def receive(msg):
            self.inputs.received(name)
            callback(msg)
        self._inputs.append(self.create_subscription(message_type, topic, receive, qos))
        return name

    def _log_note(self, level: str, message: str) -> None:
        """The extrinsics' notes ('info' or 'warning'; each logged once by its source)."""
        logger = self.get_logger()
        (logger.warning if level == "warning" else logger.info)(message)

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
        try:
            stamp = self._checked_stamp(msg.header.stamp)
            self.pipeline.on_image(camera, stamp, encoded_image(msg), self.now_seconds(),
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
        if self.params["extrinsics_source"] != "rig" and \
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
            if not static and not wants(transform.child_frame_id,
                                        transform.header.frame_id):
                continue
            t, r = transform.transform.translation, transform.transform.rotation
            try:
                stamp = stamp_seconds(transform.header.stamp)
                T = pose_from_xyz_xyzw((t.x, t.y, t.z), (r.x, r.y, r.z, r.w))
                self.tf.add(transform.header.frame_id, transform.child_frame_id, stamp, T,
                            static)
            except BadInput as error:
                self.warn_bad_input(self.pipeline.count_bad_input(error))
        self.pipeline.transforms_arrived()

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
        self.outputs.publish(result)
        timings = dict(result.timings)
        timings["publish"] = time.perf_counter() - start
        now = self.now_seconds()
        self.stats.record_output(result.stamp, now, timings, received=result.received,
                                 query_budget=result.query_budget,
                                 refined_fraction=result.refined_fraction)
        # processing: the set complete -> published (steady); latency: now - its image stamp
        # (the node's clock)
        processing = time.monotonic() - result.received if result.received is not None \
            else sum(timings.values())
        self.outputs.publish_timing(processing, now - result.stamp)

    # ----------------------------------------------------------------------- diagnostics
    def counters(self) -> dict[str, int]:
        counters = self.pipeline.counters()
        tf_counters = dict(self.tf.counters)
        tf_counters["pose_teleports"] += counters.pop("pose_teleports")
        counters.update(tf_counters)
        counters["internal_errors"] = self.internal_errors
        return counters

    def publish_diagnostics(self) -> None:
        status = self.stats.status(self.counters(), self.extrinsics.sources(self.cameras))
        if self.internal_errors:
            status["level"] = max(status["level"], 2)      # DiagnosticStatus.ERROR
            status["message"] += f"; {self.internal_errors} internal errors (see the log)"
        self.outputs.diagnostics.publish(output_messages.diagnostic_array(
            self.get_clock().now().to_msg(), f"{self.get_fully_qualified_name()}: pipeline",
            str(self.pipeline.predictor.device), status))
        self.outputs.fps.publish(Float32(data=float(self.stats.rate_hz())))

    def destroy_node(self):
        self._stop.set()
        if self.pipeline is not None:
            self.pipeline.close()
        if self._worker is not None and self._worker.is_alive():
            self._worker.join(timeout=5.0)
        return super().destroy_node()


def load_predictor(p: dict, logger) -> OnlinePredictor:
    """The checkpoint of the validated parameters ``p`` on its device, in the online step
    (its ModelConfig: ``predictor.cfg``)."""
    device = resolve_device(p["device"])
    thresholds = {k: float(p[k]) for k in ("score_threshold", "box_score_threshold")
                  if float(p[k]) >= 0}
    if not p["checkpoint"].strip():
        raise ValueError("checkpoint is empty: give a path, shipped (the packaged "
                         "model/odg_cpu.pt) or random (random weights, for tests)")
    if p["checkpoint"] == "random":
        model, cfg = load_model(None, p["preset"], device, **thresholds)
        logger.warning(f"checkpoint random: preset {p['preset']} with RANDOM WEIGHTS on "
                       f"{device}. The published occupancy and objects are meaningless.")
    else:
        path = shipped_checkpoint() if p["checkpoint"] == "shipped" else p["checkpoint"]
        model, cfg = load_model(path, device=device, **thresholds)
        logger.info(f"loaded {path} ({cfg.name}) on {device}, precision {p['precision']}")
    slow = slow_precision_warning(p["precision"], device)
    if slow:
        logger.warning(slow)
    history = int(p["history_frames"]) or None
    predictor = OnlinePredictor(model, cfg, device, max_gap=float(p["history_max_gap"]),
                                num_frames=history,
                                min_interval=float(p["history_interval"]),
                                precision=p["precision"], compile=p["compile"],
                                compiled_step=p["compiled_step"].strip() or None,
                                visibility=bool(p["visibility"]),
                                min_clear=float(p["visibility_min_clear"]),
                                query_budget=p["query_budget"])
    if p["visibility"] and cfg.calibration is None and float(p["visibility_min_clear"]) > 0:
        logger.warning(f"visibility_min_clear {p['visibility_min_clear']} has no effect: the "
                       "checkpoint has no calibration (odg export --calibrate), so only the "
                       "predicted surfaces hide space and 'observed' is less precise")
    logger.info(f"online step: {predictor.mode} mode, precision {predictor.precision}, "
                f"start-up (compile, capture) "
                f"{predictor.startup_seconds:.1f} s")
    return predictor


def params_file_problem(argv: list[str]) -> str | None:
    """What is wrong with the first unusable --params-file of the ROS arguments, or None."""
    ros_args = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    for flag, path in zip(ros_args, ros_args[1:]):
        if flag != "--params-file":
            continue
        if not Path(path).is_file():
            return f"params file {path}: no such file"
        try:
            document = yaml.safe_load(Path(path).read_text())
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
            return f"params file {path}: not YAML ({' '.join(str(error).split())})"
        if not isinstance(document, dict) or not all(
                isinstance(v, dict) and "ros__parameters" in v for v in document.values()):
            return (f"params file {path}: not a ROS params file (expected "
                    "<node or /**>: {ros__parameters: {...}})")
    return None


def rcl_message(error: Exception) -> str:
    """rcl's error text without its source locations (', at /path/file.c:123')."""
    return re.sub(r",? at [^ ,]+\.c:\d+", "", " ".join(str(error).split()))


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
    # The step's shapes are fixed: cuDNN may measure its fastest algorithms once. A process-wide
    # setting, so made here where the node's process starts (and in odg bench), not by the step.
    torch.backends.cudnn.benchmark = True
    problem = params_file_problem(argv)       # checked here: rcl would log its own error too
    if problem is None:
        try:
            rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
        except RCLError as error:             # what rcl refuses in the arguments
            problem = rcl_message(error)
    if problem is not None:
        rclpy.logging.get_logger(NODE_NAME).fatal(f"cannot start: {problem}")
        return 1
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
