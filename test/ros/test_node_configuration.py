"""What a ROS user meets when configuring odg_node: a parameter the node does not know
(params file, -p), a misspelt boolean, a params file that is missing or no ROS params file:
one FATAL line naming it (and the closest known name) and exit code 1; with
unknown_parameters: warn, a warning and the node runs. A query budget the checkpoint cannot
run is one FATAL line too."""
from __future__ import annotations

import signal
import subprocess
import sys

import pytest
import yaml


def run_node(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "odg_ros.ros.node", *args],
                          capture_output=True, text=True, timeout=timeout)


def one_fatal_line(result) -> str:
    assert result.returncode == 1, (result.stdout, result.stderr)
    lines = (result.stdout + result.stderr).strip().splitlines()
    assert len(lines) == 1 and "[FATAL]" in lines[0], lines
    return lines[0]


def params_file(path, **values):
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": values}}))
    return str(path)


def test_an_unknown_parameter_on_the_command_line_stops_the_node(rclpy_module):
    line = one_fatal_line(run_node("--ros-args", "-p", "slopp:=0.1", "-p", "device:=cpu"))
    assert "unknown parameter 'slopp'; did you mean slop?" in line


def test_misspelt_names_in_a_params_file_are_all_named(rclpy_module, tmp_path):
    path = params_file(tmp_path / "p.yaml", checkpint="random", score_treshold=0.9,
                       device="cpu")
    line = one_fatal_line(run_node("--ros-args", "--params-file", path))
    assert "unknown parameters 'checkpint'; did you mean checkpoint?, 'score_treshold'; " \
           "did you mean score_threshold?" in line


def test_a_misspelt_boolean_stops_the_node(rclpy_module):
    line = one_fatal_line(run_node("--ros-args", "-p", "visibility:=flase", "-p",
                                   "device:=cpu"))
    assert "visibility" in line and "expecting type 'BOOL'" in line


def test_a_query_budget_is_checked_before_the_model_runs(rclpy_module, tmp_path):
    """A word the schema does not know, and a fraction (a ROS double) that a checkpoint
    without trained budget heads cannot run: one FATAL line each (the latter after the
    checkpoint's "loaded" line)."""
    from odg_ros.network.checkpoint import load_model, save_checkpoint
    from odg_ros.resources import resource_path
    line = one_fatal_line(run_node("--ros-args", "-p", "query_budget:=half", "-p",
                                   "device:=cpu"))
    assert "query_budget='half': expected one of: full, auto or a fraction 0 < f <= 1" in line
    model, _ = load_model(resource_path("model/odg_cpu.pt"))
    assert model.decoder.budget_heads.is_trained            # the shipped file runs budgets
    model.decoder.budget_heads.set_trained(False)
    untrained = tmp_path / "untrained_heads.pt"
    save_checkpoint(untrained, model)
    result = run_node("--ros-args", "-p", "query_budget:=0.6", "-p", "device:=cpu", "-p",
                      f"checkpoint:={untrained}")
    lines = (result.stdout + result.stderr).strip().splitlines()
    assert result.returncode == 1 and "loaded" in lines[0] and len(lines) == 2, lines
    assert "[FATAL]" in lines[1] and "query_budget 0.6: this checkpoint's keep-score and " \
        "skip heads are not trained; use query_budget full" in lines[1]


@pytest.mark.parametrize("content, expected", [
    (None, "no such file"),
    ("slop: [1,\n", "not YAML"),
    ("slop: 0.1\n", "not a ROS params file"),
])
def test_a_params_file_that_is_missing_or_no_params_file(rclpy_module, tmp_path, content,
                                                         expected):
    path = tmp_path / "params.yaml"
    if content is not None:
        path.write_text(content)
    line = one_fatal_line(run_node("--ros-args", "--params-file", str(path)))
    assert f"params file {path}: {expected}" in line


def test_unknown_parameters_warn_only_warns(rclpy_module, tmp_path):
    path = params_file(tmp_path / "p.yaml", checkpoint="random", device="cpu",
                       unknown_parameters="warn", slopp=0.1)
    child = subprocess.Popen([sys.executable, "-m", "odg_ros.ros.node", "--ros-args",
                              "--params-file", path, "-r", "__ns:=/odg_warn_test"],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        for line in child.stdout:
            lines.append(line)
            if "outputs in" in line:                 # started
                break
        text = "".join(lines)
        assert "[WARN]" in text and "unknown parameter 'slopp'; did you mean slop?" in text
        assert "outputs in" in text, text
    finally:
        child.send_signal(signal.SIGINT)
        assert child.wait(timeout=30) == 0


def test_the_node_runs_the_visibility_min_clear_it_is_given(rclpy_module):
    """visibility_min_clear reaches the step; a checkpoint without a calibration (no hazard)
    says at start that it has no effect."""
    from odg_ros.online import parameters
    from odg_ros.ros.node import load_predictor

    class Logger:
        def __init__(self):
            self.lines = []

        def __getattr__(self, level):
            return lambda message: self.lines.append((level, message))

    p = {name: rule.default for name, rule in parameters.load_schema().items()}
    p.update(checkpoint="random", preset="odg_cpu", device="cpu", visibility_min_clear=0.5)
    logger = Logger()
    predictor = load_predictor(p, logger)
    assert predictor.min_clear == 0.5
    assert predictor.online_step.visibility.min_clear == 0.5
    assert any(level == "warning" and "visibility_min_clear 0.5 has no effect" in message
               for level, message in logger.lines)


def test_intrinsics_from_a_rig_file_that_cannot_give_them(rclpy_module, tmp_path):
    """intrinsics_source rig with cameras the rig file does not have, or a rig file without
    intrinsics: one FATAL line that says which, before the model loads."""
    line = one_fatal_line(run_node(
        "--ros-args", "-p", "intrinsics_source:=rig", "-p", "device:=cpu", "-p",
        "camera_names:=[cam_front, cam_front_right, cam_front_left, cam_back, cam_back_left, "
        "cam_back_right]"))
    assert "cameras ['cam_front'," in line and "are not in the rig file " \
        "config/rig_nuscenes.yaml (intrinsics_source rig; it has ['CAM_FRONT'," in line
    from odg_ros.resources import resource_path
    rig = yaml.safe_load(resource_path("config/rig_nuscenes.yaml").read_text())
    del rig["cameras"]["CAM_BACK"]["intrinsics"]
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(rig))
    line = one_fatal_line(run_node("--ros-args", "-p", "intrinsics_source:=rig", "-p",
                                   f"rig_file:={path}", "-p", "device:=cpu"))
    assert f"{path}: camera CAM_BACK: no 'intrinsics'" in line
