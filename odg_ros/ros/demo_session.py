"""The ROS half of ``odg demo``: odg_node and odg replay in processes of their own, and a
planner stand-in in this one that receives every output (odg_ros/demo/ defines the numbers).

    odg_node --ros-args --params-file config/odg.yaml -p checkpoint:=CKPT -p use_sim_time:=true
    odg replay BAG --clock --rate R --wait-for-subscribers S
    planner stand-in: ~/occupancy, ~/objects, ~/fps, /diagnostics (+ /clock to time the
                      inputs, /odom as a planner would)

All three use the loopback-only DDS set-up of ``dds.py``. Every child process is stopped in
every case (SIGINT, then SIGKILL after a timeout); their output goes to ``node.log`` and
``replay.log`` in the demo folder, and a failure quotes the tail of the log concerned.

Under ``use_sim_time`` the node's clock is the bag's ``/clock``, and its diagnostics timer runs
on that clock: when the bag ends, the clock stops and so do the diagnostics. So that the node
reports its final counters (sets dropped after the last report), the stand-in keeps the
simulated clock running, at real-time speed from the bag's last stamp, once the replay has
exited and the last output has arrived.
"""
from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..bags import layout
from ..demo import DemoError
from ..demo.records import CameraSets, ReceivedGrid, SessionRecord
from ..resources import resource_path
from .dds import localhost_dds_env, use_localhost_dds

NODE_NAME = "odg_node"                 # pinned on the node's command line (-r __node:=...)
NODE = f"/{NODE_NAME}"
NODE_READY_TIMEOUT_S = 240.0           # torch import + checkpoint load on a busy 2-core machine
REPLAY_START_TIMEOUT_S = 120.0         # interpreter start + waiting for subscribers
DRAIN_TIMEOUT_S = 60.0                 # last set still in the node after the replay ended
FINAL_DIAGNOSTICS_TIMEOUT_S = 15.0
STOP_TIMEOUT_S = 10.0


def _die_with_parent() -> None:
    """In the child before exec (Linux): SIGTERM it when the demo process dies, even by
    SIGKILL, so that no node keeps running orphaned. Elsewhere ``stop`` has to do."""
    if sys.platform.startswith("linux"):
        import ctypes
        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


class ChildProcess:
    """A child process whose stdout + stderr go to a log file; ``stop`` always ends it."""

    def __init__(self, name: str, command: list[str], log_path: Path, env: dict):
        self.name = name
        self.log_path = Path(log_path)
        self._log = open(self.log_path, "w")
        self.process = subprocess.Popen(command, stdout=self._log, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL, env=env,
                                        preexec_fn=_die_with_parent)

    def poll(self) -> int | None:
        return self.process.poll()

    def tail(self, lines: int = 30) -> str:
        self._log.flush()
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(text[-lines:])

    def failure(self, what: str) -> DemoError:
        return DemoError(f"{what}. Last lines of {self.log_path}:\n{self.tail()}")

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> int | None:
        """SIGINT (a clean rclpy shutdown), then SIGKILL after ``timeout`` seconds."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._log.close()
        return self.process.returncode


def node_command(checkpoint: Path, precision: str = "auto", device: str = "auto") -> list[str]:
    return [sys.executable, "-m", "odg_ros.ros.node", "--ros-args",
            "--params-file", str(resource_path("config/odg.yaml")),
            "-r", f"__node:={NODE_NAME}",
            "-p", f"checkpoint:={checkpoint}",
            "-p", f"precision:={precision}",
            "-p", f"device:={device}",
            "-p", "use_sim_time:=true"]


def replay_command(bag: Path, rate: float) -> list[str]:
    return [sys.executable, "-m", "odg_ros.commands", "replay", str(bag), "--clock", "--quiet",
            "--rate", repr(float(rate)),
            "--wait-for-subscribers", str(int(REPLAY_START_TIMEOUT_S / 2))]


def _stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class PlannerStandIn:
    """Subscribes to the node's outputs like a planner would and records them (no ROS types
    leave this class: see odg_ros.demo.records.SessionRecord)."""

    def __init__(self, context, record: SessionRecord):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock
        from std_msgs.msg import Float32

        from odg_ros_msgs.msg import DynamicObjectArray, SemanticVoxelGrid

        self.record = record
        self.node = rclpy.create_node("odg_demo_planner", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        n = self.node
        n.create_subscription(SemanticVoxelGrid, f"{NODE}/occupancy", self.on_grid, reliable)
        n.create_subscription(DynamicObjectArray, f"{NODE}/objects", self.on_objects, reliable)
        n.create_subscription(Float32, f"{NODE}/fps", self.on_fps, reliable)
        n.create_subscription(DiagnosticArray, "/diagnostics", self.on_diagnostics, reliable)
        n.create_subscription(Clock, layout.CLOCK_TOPIC, self.on_clock, reliable)
        # A planner follows the ego odometry; it is also the one subscriber of the bag's /odom
        # (the node takes its pose from /tf), which `odg replay --wait-for-subscribers` wants.
        n.create_subscription(Odometry, layout.ODOM_TOPIC, self.on_odometry, reliable)
        self.clock_publisher = n.create_publisher(Clock, layout.CLOCK_TOPIC, 10)
        self._Clock = Clock
        self.latest_clock_ns = None
        self.diagnostics_received = 0
        self.diagnostics_wall_s = None
        self.error = None

    # ------------------------------------------------------------------------- callbacks
    def on_grid(self, msg) -> None:
        now = time.monotonic()
        shape = (msg.size_x, msg.size_y, msg.size_z)
        if msg.memory_order != "xyz_c" or len(msg.labels) != int(np.prod(shape)):
            self.error = (f"unexpected grid: memory_order {msg.memory_order!r}, "
                          f"{len(msg.labels)} labels for {shape}")
            return
        labels = np.frombuffer(bytes(msg.labels), dtype=np.uint8).reshape(shape)
        observed = None
        if len(msg.observed) == labels.size:
            observed = np.frombuffer(bytes(msg.observed), dtype=np.uint8).reshape(shape) != 0
        self.record.grids.append(ReceivedGrid(_stamp_ns(msg.header.stamp), now, labels,
                                              observed))

    def on_objects(self, msg) -> None:
        self.record.objects.append((_stamp_ns(msg.header.stamp), len(msg.objects)))

    def on_fps(self, msg) -> None:
        self.record.fps_samples.append(float(msg.data))

    def on_diagnostics(self, msg) -> None:
        for status in msg.status:
            if status.name.startswith(f"{NODE}:"):
                self.record.diagnostics = {kv.key: kv.value for kv in status.values}
                self.record.diagnostics_message = status.message
                self.diagnostics_received += 1
                self.diagnostics_wall_s = time.monotonic()

    def on_clock(self, msg) -> None:
        stamp = _stamp_ns(msg.clock)
        self.record.clock_wall.setdefault(stamp, time.monotonic())
        if self.latest_clock_ns is None or stamp > self.latest_clock_ns:
            self.latest_clock_ns = stamp

    def on_odometry(self, msg) -> None:
        self.record.odometry_messages += 1

    # ---------------------------------------------------------------------------- helpers
    def spin(self, seconds: float = 0.05) -> None:
        self.executor.spin_once(timeout_sec=seconds)
        if self.error:
            raise DemoError(self.error)

    def publish_clock(self, stamp_ns: int) -> None:
        from builtin_interfaces.msg import Time
        self.clock_publisher.publish(self._Clock(clock=Time(
            sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)))

    def node_is_up(self) -> bool:
        """The node has loaded its model (it creates its publishers and subscriptions after
        that). Not its diagnostics: their timer runs on the simulated clock, which only
        starts with the replay."""
        return (self.node.count_publishers(f"{NODE}/occupancy") > 0
                and self.node.count_subscribers(layout.image_topic("CAM_FRONT")) > 0)

    def destroy(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()


def run_session(bag: Path, checkpoint: Path, sets: CameraSets, out_dir: Path, rate: float,
                progress: bool = True, log=print, precision: str = "auto",
                device: str = "auto") -> SessionRecord:
    """Start the node, wait until it is up, replay the bag, receive every output, collect the
    node's final diagnostics; stop everything. Raises DemoError on any failure."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    use_localhost_dds()          # this process's participant (before rclpy.init) ...
    env = localhost_dds_env()    # ... and the children's
    env["PYTHONUNBUFFERED"] = "1"

    record = SessionRecord()
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = replay = planner = None
    try:
        planner = PlannerStandIn(context, record)
        start = time.monotonic()
        node = ChildProcess("odg_node", node_command(checkpoint, precision, device),
                            out_dir / "node.log", env)
        log(f"odg_node started (pid {node.process.pid}, log {node.log_path}); waiting for it "
            "to load the checkpoint")
        _wait_until_up(planner, node, progress)
        record.timings["node_start"] = time.monotonic() - start

        start = time.monotonic()
        replay = ChildProcess("odg replay", replay_command(bag, rate), out_dir / "replay.log",
                              env)
        _follow_replay(planner, node, replay, sets, rate, progress)
        record.timings["replay"] = time.monotonic() - start

        start = time.monotonic()
        _wait_for_last_set(planner, node, sets)
        _collect_final_counters(planner, sets)
        record.timings["drain"] = time.monotonic() - start
        if node.poll() is not None:
            raise node.failure(f"odg_node exited with code {node.poll()}")
        return record
    finally:
        for child in (replay, node):
            if child is not None:
                child.stop()
        if planner is not None:
            planner.destroy()
        context.try_shutdown()


def _wait_until_up(planner: PlannerStandIn, node: ChildProcess, progress: bool) -> None:
    """Until the node has loaded its checkpoint and subscribed (raises when it died or hung)."""
    start = shown = time.monotonic()
    with tqdm(desc="starting odg_node", bar_format="{desc}: {elapsed}",
              disable=not progress) as bar:
        while not planner.node_is_up():
            planner.spin()
            if time.monotonic() - shown > 1.0:
                bar.refresh()
                shown = time.monotonic()
            if node.poll() is not None:
                raise node.failure(f"odg_node exited with code {node.poll()} while starting")
            if time.monotonic() - start > NODE_READY_TIMEOUT_S:
                raise node.failure(f"odg_node was not up after {NODE_READY_TIMEOUT_S:.0f} s")


def _follow_replay(planner: PlannerStandIn, node: ChildProcess, replay: ChildProcess,
                   sets: CameraSets, rate: float, progress: bool) -> None:
    """Receive the outputs while the replay runs, with the sets replayed so far as progress."""
    record = planner.record
    start = shown = time.monotonic()
    deadline = start + REPLAY_START_TIMEOUT_S + sets.duration_s() / rate * 1.5
    references = sets.reference_ns
    bar = tqdm(total=len(references), desc=f"replay at {rate:g}x -> odg_node",
               unit="set", disable=not progress)
    try:
        while replay.poll() is None:
            planner.spin()
            if node.poll() is not None:
                raise node.failure(f"odg_node exited with code {node.poll()} during the "
                                   "replay")
            if time.monotonic() > deadline:
                raise replay.failure("the replay did not finish in time")
            if planner.latest_clock_ns is not None and time.monotonic() - shown > 0.5:
                shown = time.monotonic()
                bar.n = int(np.searchsorted(references, planner.latest_clock_ns, "right"))
                bar.set_postfix_str(f"grids out {len(record.grids)}", refresh=False)
                bar.refresh()
        record.replay_exit_code = replay.poll()
        if record.replay_exit_code != 0:
            raise replay.failure(f"odg replay exited with code {record.replay_exit_code}")
        bar.n = len(references)
        bar.refresh()
    finally:
        bar.close()
    if replay.tail().find("no subscriber after") >= 0:
        record.warnings.append("the replay started before every topic had a subscriber "
                               f"(see {replay.log_path})")


def _wait_for_last_set(planner: PlannerStandIn, node: ChildProcess, sets: CameraSets) -> None:
    """The sets still in the node when the replay ended: wait for the last one's grid."""
    record = planner.record
    start = time.monotonic()
    references = sets.reference_ns
    last = int(references[sets.complete_ns >= 0][-1]) if sets.num_complete else None
    while (last is not None and not any(g.stamp_ns == last for g in record.grids)
           and time.monotonic() - start < DRAIN_TIMEOUT_S):
        planner.spin()
        if node.poll() is not None:
            raise node.failure(f"odg_node exited with code {node.poll()}")
    if last is not None and not any(g.stamp_ns == last for g in record.grids):
        record.warnings.append(f"no grid for the last camera set after "
                               f"{DRAIN_TIMEOUT_S:.0f} s")


def _collect_final_counters(planner: PlannerStandIn, sets: CameraSets) -> None:
    """The node's diagnostics after its last output (see the module docstring): the clock is
    advanced until one arrives that counts every output received."""
    record = planner.record
    final = time.monotonic()
    clock_ns = planner.latest_clock_ns or int(sets.reference_ns[-1])
    seen = planner.diagnostics_received
    while time.monotonic() - final < FINAL_DIAGNOSTICS_TIMEOUT_S:
        clock_ns += 50_000_000
        planner.publish_clock(clock_ns)
        planner.spin(0.05)
        if (planner.diagnostics_received > seen
                and int(record.diagnostics.get("outputs", "-1")) >= len(record.grids)):
            return
    record.warnings.append("no diagnostics from the node after its last output; "
                           "the drop counters may miss the last sets")
