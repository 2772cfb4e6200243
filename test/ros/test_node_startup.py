"""odg_node's start-up as a user meets it: `--help` prints the parameters and exits 0 without
starting ROS; a corrupt checkpoint or a bad parameter is one FATAL line and exit code 1."""
from __future__ import annotations

import signal
import subprocess
import sys

import pytest

from testing.helpers import write_tiny_checkpoint


def run_node(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "odg_ros.ros.node", *args],
                          capture_output=True, text=True, timeout=timeout)


def test_help_prints_the_parameters_and_exits():
    result = run_node("--help")
    assert result.returncode == 0, result.stderr
    assert "checkpoint (string, default shipped)" in result.stdout
    assert ("precision (string, default auto; one of: auto, fp32, bf16, bf16-encoder, int8-encoder, fp16)"
            in result.stdout)
    assert result.stderr == ""                   # no ROS logging: nothing was started


def test_a_truncated_checkpoint_is_one_fatal_line(rclpy_module, tmp_path):
    # (the other unusable files: test_checkpoint.py, same error path)
    path = write_tiny_checkpoint(tmp_path / "tiny.pt")
    path.write_bytes(path.read_bytes()[:4096])
    result = run_node("--ros-args", "-p", f"checkpoint:={path}", "-p", "device:=cpu")
    assert result.returncode == 1
    lines = (result.stdout + result.stderr).strip().splitlines()
    assert len(lines) == 1, lines
    assert "[FATAL]" in lines[0] and str(path) in lines[0]


def test_by_default_the_shipped_checkpoint_is_loaded(rclpy_module):
    from odg_ros.resources import resource_path
    child = subprocess.Popen([sys.executable, "-m", "odg_ros.ros.node", "--ros-args", "-p",
                              "device:=cpu", "-r", "__ns:=/odg_default_test"],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        for line in child.stdout:                # ends when the node exits
            lines.append(line)
            if "outputs in" in line:             # the last start-up line
                break
        text = "".join(lines)
        assert f"loaded {resource_path('model/odg_cpu.pt')} (odg_cpu)" in text, text
        assert "RANDOM" not in text
    finally:
        child.send_signal(signal.SIGINT)
        assert child.wait(timeout=30) == 0


def test_a_node_that_failed_to_start_shuts_down_cleanly(ros_context, monkeypatch):
    # rclpy destroys every node of a context it shuts down, a half-built one included (kept
    # alive here by the traceback): that must not raise a second error.
    from odg_ros.ros import node as node_module

    def broken_load_model(*args, **kwargs):
        raise RuntimeError("a bug while loading")
    monkeypatch.setattr(node_module, "load_model", broken_load_model)
    with pytest.raises(RuntimeError, match="a bug while loading") as failure:
        node_module.OdgNode(context=ros_context)
    # the constructor's own error, raised where it happened, with no second one behind it
    assert failure.type is RuntimeError and failure.traceback[-1].name == "broken_load_model"
    assert failure.value.__context__ is None and failure.value.__cause__ is None
    ros_context.try_shutdown()                  # destroys the half-built node: raises nothing
    assert not ros_context.ok()
