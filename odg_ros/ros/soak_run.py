"""Soak runs: a real odg_node process fed by ``odg replay --loop --clock`` for a while, watched
as a planner and an operator would watch it. What is recorded (plain values, JSON-ready) is
summarised by odg_ros/bench/soak_report.py; ``odg soak`` runs both.

Per run: the node's resident memory (``/proc/PID/status`` VmRSS) every ``rss_period`` s; every
output's stamp (``~/objects``, published with every output) and its wall latency (from its
reference camera image reaching this process to it reaching this process: no clock of the
node's, whose bag time lags when its intake is saturated), the node's own pipeline latency
and processing time for it (``~/debug/pipeline_latency_ms``, ``~/debug/processing_time_ms``,
in the same order); every ``/diagnostics`` status of the node (level, message, counters); the
bags' time spans and the replay's "playing" line for each bag it starts; whether the node
died, and how. Times are seconds of wall time from the replay's first message.

The node and the replay run in a ROS domain of the caller's choosing (``ROS_DOMAIN_ID``); DDS
stays on this machine (odg_ros.ros.dds). Only the topics the node subscribes to are played
(found in the ROS graph once the node is up), unless ``topics`` are given.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Sequence

from .dds import localhost_dds_env

NODE_NAME = "odg_node"
NAMESPACE = "/odg_soak"
IMAGE_MEMORY_S = 120.0     # how long the watcher remembers when each reference image came
IN_FLIGHT_S = 0.5          # a killed node's last messages arrive within this
_PLAYING = re.compile(r"playing (\d+)/(\d+): (\S+)")


def soak_node_command(node_args: Sequence[str], namespace: str) -> list[str]:
    """odg_node with the caller's ROS arguments, in ``namespace``, on the bag's clock."""
    args = list(node_args)
    ros_args = args[args.index("--ros-args") + 1:] if "--ros-args" in args else args
    return [sys.executable, "-m", "odg_ros.ros.node", "--ros-args", *ros_args,
            "-r", f"__ns:={namespace}", "-p", "use_sim_time:=true"]


def rss_bytes(pid: int) -> int | None:
    """The resident set size of a process (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def stop_process(child: subprocess.Popen, timeout: float = 20.0) -> int:
    """SIGINT, then SIGKILL after ``timeout`` s; the exit code."""
    if child.poll() is None:
        child.send_signal(signal.SIGINT)
        try:
            child.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
    return child.returncode


class NodeProcess:
    """odg_node in a process of its own, its log in ``log_path``."""

    def __init__(self, node_args: Sequence[str], namespace: str, log_path: Path,
                 env: dict | None = None):
        self.namespace = namespace.rstrip("/")
        self.name = f"{self.namespace}/{NODE_NAME}"
        self.log_path = Path(log_path)
        self.command = soak_node_command(node_args, self.namespace)
        self.env = env
        self.process: subprocess.Popen | None = None
        self.started = None

    def start(self) -> "NodeProcess":
        with open(self.log_path, "a") as log:
            self.process = subprocess.Popen(self.command, stdout=log, stderr=subprocess.STDOUT,
                                            env=self.env)
        self.started = time.monotonic()
        return self

    @property
    def pid(self) -> int:
        return self.process.pid

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def kill(self) -> None:
        """SIGKILL: what a crash or an out-of-memory kill does."""
        self.process.kill()
        self.process.wait()

    def stop(self) -> int:
        return stop_process(self.process)

    def log_tail(self, chars: int = 3000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-chars:]
        except FileNotFoundError:
            return ""


class ReplayProcess:
    """``odg replay BAGS --clock --loop --rate R`` in a process of its own; its "playing"
    lines, timed as they come."""

    def __init__(self, bags: Sequence[Path], rate: float, topics: Sequence[str],
                 remap: Sequence[str] = (), env: dict | None = None):
        self.command = [sys.executable, "-m", "odg_ros.commands", "replay",
                        *map(str, bags), "--clock", "--loop", "--rate", repr(float(rate)),
                        "--quiet", "--wait-for-subscribers", "60", "--topics", *topics]
        if remap:
            self.command += ["--remap", *remap]
        self.env = env
        self.announced: list[tuple[float, int, str]] = []     # (monotonic, bag index, path)
        self.errors: list[str] = []
        self.process: subprocess.Popen | None = None

    def start(self) -> "ReplayProcess":
        self.process = subprocess.Popen(self.command, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.PIPE, text=True, env=self.env)
        threading.Thread(target=self._read, daemon=True, name="replay_lines").start()
        return self

    def _read(self) -> None:
        for line in self.process.stderr:
            found = _PLAYING.search(line)
            if found:
                self.announced.append((time.monotonic(), int(found.group(1)), found.group(3)))
            elif line.strip():
                self.errors.append(line.rstrip())

    def stop(self) -> int:
        return stop_process(self.process)


class Watcher:
    """What a planner and an operator see of the node: its outputs, their latency and
    processing times, and its diagnostics, each with the monotonic time it arrived."""

    def __init__(self, rclpy, context, node_name: str):
        from diagnostic_msgs.msg import DiagnosticArray
        from odg_ros_msgs.msg import DynamicObjectArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock
        from std_msgs.msg import Float64

        self.node_name = node_name
        self.node = rclpy.create_node("odg_soak_watcher", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        # (t, stamp s, wall ms since each arrival here of an image with its stamp)
        self.outputs: list[tuple[float, float, list[float]]] = []
        self.latency_ms: list[tuple[float, float]] = []       # (t, node clock ms)
        self.processing_ms: list[tuple[float, float]] = []    # (t, steady ms)
        self.diagnostics: list[tuple[float, int, str, dict]] = []
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(DynamicObjectArray, f"{node_name}/objects",
                                      self._output, reliable)
        self.node.create_subscription(Float64, f"{node_name}/debug/pipeline_latency_ms",
                                      lambda msg: self._timing(self.latency_ms, msg), reliable)
        self.node.create_subscription(Float64, f"{node_name}/debug/processing_time_ms",
                                      lambda msg: self._timing(self.processing_ms, msg),
                                      reliable)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._diagnostics, 50)
        self.images: dict[int, list[float]] = {}    # reference image stamp (us) -> arrivals
        self.first_clock: float | None = None      # when the replay's first message came
        self.clock_subscription = self.node.create_subscription(Clock, "/clock",
                                                                self._first_clock, 10)

    def watch_reference_images(self, topic: str, compressed: bool) -> None:
        """The arrival of each image of the reference camera (whose stamp the outputs
        carry): an output's wall latency is its arrival minus its image's, both seen here.
        Raw CDR: only the header stamp is read."""
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import CompressedImage, Image
        self.node.create_subscription(CompressedImage if compressed else Image, topic,
                                      self._image, qos_profile_sensor_data, raw=True)

    def _image(self, raw: bytes) -> None:
        now = time.monotonic()
        # CDR: a 4-byte encapsulation header, then std_msgs/Header: int32 sec, uint32 nanosec
        order = "little" if raw[1] == 1 else "big"
        sec = int.from_bytes(raw[4:8], order, signed=True)
        stamp = sec * 1_000_000 + int.from_bytes(raw[8:12], order) // 1000
        # a looping replay brings the same stamp again: every arrival of the last minutes
        arrivals = [t for t in self.images.pop(stamp, ()) if t > now - IMAGE_MEMORY_S]
        self.images[stamp] = arrivals + [now]
        if len(self.images) > 8192:                # oldest first (insertion order)
            for old in list(self.images)[:2048]:
                del self.images[old]

    def _first_clock(self, msg) -> None:
        if self.first_clock is None:
            self.first_clock = time.monotonic()

    @staticmethod
    def _timing(series: list, msg) -> None:
        series.append((time.monotonic(), float(msg.data)))

    def _output(self, msg) -> None:
        now = time.monotonic()
        sec, nanosec = msg.header.stamp.sec, msg.header.stamp.nanosec
        arrivals = self.images.get(sec * 1_000_000 + nanosec // 1000, [])
        self.outputs.append((now, sec + nanosec * 1e-9, [1e3 * (now - t) for t in arrivals]))

    def _diagnostics(self, array) -> None:
        for status in array.status:
            if status.name.startswith(self.node_name + ":"):
                level = status.level
                level = int.from_bytes(level, "little") if isinstance(level, bytes) \
                    else int(level)
                counters = {kv.key: int(kv.value) for kv in status.values
                            if kv.value.isdigit()}
                self.diagnostics.append((time.monotonic(), level, status.message, counters))

    def spin(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return
            self.executor.spin_once(timeout_sec=min(left, 0.05))

    def node_inputs(self) -> list[str]:
        """The topics the node subscribes to (but /clock and parameter events)."""
        namespace, _, name = self.node_name.rpartition("/")
        try:
            found = self.node.get_subscriber_names_and_types_by_node(name, namespace or "/")
        except Exception:            # not discovered yet
            return []
        return sorted(t for t, _ in found if t not in ("/clock", "/parameter_events"))

    def destroy(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def wait_for_node(watcher: Watcher, node: NodeProcess, timeout: float) -> list[str]:
    """Until the node subscribes to its inputs (its model loaded): those topics. Raises
    RuntimeError when it exits or does not come up."""
    deadline = time.monotonic() + timeout
    inputs: list[str] = []
    while time.monotonic() < deadline:
        watcher.spin(0.2)
        if not node.alive():
            raise RuntimeError(f"odg_node exited with {node.process.returncode}:\n"
                               f"{node.log_tail()}")
        now = watcher.node_inputs()
        if now and now == inputs and watcher.node.count_publishers(
                f"{node.name}/objects"):
            return now                           # the same twice: all are created
        inputs = now
    raise RuntimeError(f"odg_node did not come up in {timeout:.0f} s:\n{node.log_tail()}")


def replayed_topics(bag_topics: Sequence[str], node_inputs: Sequence[str],
                    remap: Sequence[str] = ()) -> list[str]:
    """The bags' topics (as they name them) that reach one of the node's inputs after the
    replay's remapping rules (plain OLD:=NEW topic renames)."""
    rules = dict(rule.split(":=", 1) for rule in remap if ":=" in rule)
    wanted = set(node_inputs)
    chosen = []
    for topic in bag_topics:
        absolute = topic if topic.startswith("/") else "/" + topic
        if rules.get(absolute, rules.get(topic, absolute)) in wanted:
            chosen.append(topic)
    if not chosen:
        raise ValueError(f"no topic of the bags reaches the node (it subscribes to "
                         f"{', '.join(node_inputs)})")
    return chosen


class Session:
    """The node started and watched, then the bags replayed into it in a loop (``start``);
    ``close`` stops both. ``reference_image``: (the reference camera's image topic,
    compressed or not), for the wall latency of each output."""

    def __init__(self, bags: Sequence[Path], rate: float, node_args: Sequence[str], *,
                 log_path: Path, namespace: str = NAMESPACE,
                 topics: Sequence[str] | None = None, remap: Sequence[str] = (),
                 reference_image: tuple[str, bool] | None = None,
                 startup_timeout: float = 600.0):
        from .replay import open_bags
        self.env = localhost_dds_env()
        self.opened = open_bags(bags)
        self.rate, self.node_args, self.log_path = float(rate), list(node_args), log_path
        self.namespace, self.topics, self.remap = namespace, topics, list(remap)
        self.reference_image, self.startup_timeout = reference_image, startup_timeout
        self.node = self.context = self.watcher = self.replay = None
        self.start_time = None          # monotonic: the replay's first message

    def bags(self) -> list[dict]:
        return [{"path": str(b.path), "start": b.start_ns * 1e-9, "end": b.end_ns * 1e-9}
                for b in self.opened]

    def start(self) -> "Session":
        import rclpy
        self.node = NodeProcess(self.node_args, self.namespace, self.log_path,
                                self.env).start()
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context)
        self.watcher = Watcher(rclpy, self.context, self.node.name)
        if self.reference_image is not None:
            self.watcher.watch_reference_images(*self.reference_image)
        inputs = wait_for_node(self.watcher, self.node, self.startup_timeout)
        self.node_startup_s = time.monotonic() - self.node.started
        if self.topics is None:
            self.topics = replayed_topics(sorted({t for b in self.opened for t in b.topics}),
                                          inputs, self.remap)
        self.replay = ReplayProcess([b.path for b in self.opened], self.rate, self.topics,
                                    self.remap, self.env).start()
        while self.watcher.first_clock is None:   # the replay waits for its subscribers
            self.watcher.spin(0.1)
            if self.replay.process.poll() is not None:
                raise RuntimeError("odg replay exited: " + "\n".join(self.replay.errors[-5:]))
        # /clock is busy (a message per stamp of the bag) and not needed any more
        self.watcher.node.destroy_subscription(self.watcher.clock_subscription)
        self.start_time = self.watcher.first_clock
        return self

    def elapsed(self) -> float:
        return time.monotonic() - self.start_time

    def finish(self, record: dict) -> None:
        """Stop the replay, collect the outputs still coming, and add the records."""
        self.replay.stop()
        if self.node.alive():
            _drain(self.watcher)
        _relative(record, self.watcher, self.replay, self.start_time)

    def close(self, record: dict) -> None:
        if self.replay is not None:
            self.replay.stop()
        if self.node is not None:
            record.setdefault("node_exit_after_stop", self.node.stop() if self.node.alive()
                              else self.node.process.returncode)
            record["log_tail"] = self.node.log_tail()
        if self.watcher is not None:
            self.watcher.destroy()
        if self.context is not None:
            self.context.try_shutdown()


def soak_run(bags: Sequence[Path], rate: float, seconds: float, node_args: Sequence[str], *,
             log_path: Path, topics: Sequence[str] | None = None, remap: Sequence[str] = (),
             rss_period: float = 1.0, history_max_gap: float = 1.0,
             reference_image: tuple[str, bool] | None = None,
             tick: Callable[[float], None] | None = None) -> dict:
    """One soak run: the node started, the bags replayed in a loop at ``rate`` for ``seconds``
    of wall time from the first message, then both stopped. ``tick(elapsed)`` is called about
    once a second (progress). ``history_max_gap``: the node's, kept with the records (a
    longer gap between outputs restarts its history). Returns the records (see the module
    doc)."""
    session = Session(bags, rate, node_args, log_path=log_path, topics=topics, remap=remap,
                      reference_image=reference_image)
    record = {"rate": float(rate), "seconds": float(seconds), "rss": [], "node_exit": None,
              "history_max_gap": float(history_max_gap), "bags": session.bags()}
    try:
        session.start()
        node, watcher = session.node, session.watcher
        record.update(node_command=node.command, node_startup_s=session.node_startup_s,
                      topics=list(session.topics))
        next_sample = time.monotonic()
        while (elapsed := session.elapsed()) < seconds and node.alive():
            if time.monotonic() >= next_sample:
                rss = rss_bytes(node.pid)
                if rss is not None and node.alive():
                    record["rss"].append((elapsed, rss))
                next_sample += rss_period
                if tick is not None:
                    tick(elapsed)
            watcher.spin(min(0.2, max(0.0, next_sample - time.monotonic())))
        record["wall_s"] = session.elapsed()
        record["node_exit"] = node.process.returncode if not node.alive() else None
        session.finish(record)
    finally:
        session.close(record)
    return record


def restart_run(bags: Sequence[Path], node_args: Sequence[str], *, log_path: Path,
                restarts: int = 3, outputs_before_kill: int = 3, timeout: float = 300.0,
                reference_image: tuple[str, bool] | None = None,
                topics: Sequence[str] | None = None, remap: Sequence[str] = ()) -> dict:
    """The node killed with SIGKILL mid-bag (after ``outputs_before_kill`` outputs) and
    started again, ``restarts`` times, the bags replayed at 1x all along. Per restart: when
    the node was killed and the new one started, seconds from its start to its first
    diagnostics (up) and to its first output, and where its reports and outputs begin in
    the records. Times as in ``soak_run``'s records."""
    session = Session(bags, 1.0, node_args, log_path=log_path, topics=topics, remap=remap,
                      reference_image=reference_image, startup_timeout=timeout)
    record = {"rate": 1.0, "restarts": [], "bags": session.bags(), "rss": [],
              "node_exit": None}
    try:
        session.start()
        watcher = session.watcher
        for _ in range(restarts):
            seen = len(watcher.outputs)
            _spin_until(watcher, lambda: len(watcher.outputs) >= seen + outputs_before_kill,
                        timeout, "outputs before the kill")
            session.node.kill()
            killed = time.monotonic()
            outputs, reports = len(watcher.outputs), len(watcher.diagnostics)
            session.node = NodeProcess(session.node_args, session.namespace, log_path,
                                       session.env).start()
            started = session.node.started
            # the new node's first report (one of the killed node's may still come in)
            # reports arriving this long after the SIGKILL are the new node's (the killed
            # one's last may still be in flight; the new one takes seconds to start)
            not_before = killed + IN_FLIGHT_S
            _spin_until(watcher, lambda: _first_report(watcher, reports, not_before)
                        is not None, timeout, "diagnostics from the restarted node",
                        session.node)
            reports = _first_report(watcher, reports, not_before)
            up = watcher.diagnostics[reports][0]
            _spin_until(watcher, lambda: len(watcher.outputs) > outputs, timeout,
                        "the restarted node's first output", session.node)
            record["restarts"].append({
                "killed_s": killed - session.start_time, "started_s": started -
                session.start_time, "up_after_s": up - started,
                "first_output_after_s": watcher.outputs[outputs][0] - started,
                "first_output_index": outputs,
                "first_report_index": reports})
        record["wall_s"] = session.elapsed()
        session.finish(record)
    finally:
        session.close(record)
    return record


def _first_report(watcher: Watcher, after: int, not_before: float) -> int | None:
    """The index of the first diagnostics report from ``after`` on that arrived at
    ``not_before`` (monotonic seconds) or later."""
    return next((i for i in range(after, len(watcher.diagnostics))
                 if watcher.diagnostics[i][0] >= not_before), None)


def _spin_until(watcher: Watcher, done: Callable[[], bool], timeout: float, what: str,
                node: NodeProcess | None = None) -> None:
    deadline = time.monotonic() + timeout
    while not done():
        if time.monotonic() > deadline:
            raise RuntimeError(f"no {what} in {timeout:.0f} s")
        if node is not None and not node.alive():
            raise RuntimeError(f"odg_node exited with {node.process.returncode}:\n"
                               f"{node.log_tail()}")
        watcher.spin(0.1)


def _drain(watcher: Watcher, timeout: float = 30.0) -> None:
    """With the replay stopped: until no output has come for two diagnostics periods and a
    step (the longest processing time seen), so that a set the model was running on comes
    out and the last diagnostics count it: every reset they show then has its output."""
    stopped = time.monotonic()
    deadline = stopped + timeout
    while time.monotonic() < deadline:
        watcher.spin(0.2)
        times = [d[0] for d in watcher.diagnostics[-3:]]
        period = max(1.0, times[-1] - times[0]) / 2 if len(times) == 3 else 1.0
        step = max((ms for _, ms in watcher.processing_ms), default=0.0) * 1e-3
        last = max([stopped] + [t for t, *_ in watcher.outputs[-1:]])
        if time.monotonic() - last > 2 * period + 1.5 * step:
            return


def _relative(record: dict, watcher: Watcher, replay: ReplayProcess, start: float) -> None:
    """The watcher's and the replay's records, times in seconds from ``start``."""
    record["outputs"] = [(t - start, stamp, ms) for t, stamp, ms in watcher.outputs]
    for name in ("latency_ms", "processing_ms"):
        record[name] = [(t - start, value) for t, value in getattr(watcher, name)]
    record["diagnostics"] = [(t - start, level, message, counters)
                             for t, level, message, counters in watcher.diagnostics]
    record["announced"] = [(t - start, index, path) for t, index, path in replay.announced]
    record["replay_errors"] = list(replay.errors)
    record["domain_id"] = os.environ.get("ROS_DOMAIN_ID", "0")
