"""Every command in README.md works as written: each is run here at tiny sizes (a tiny
synthetic world in the nuScenes v1.0-mini layout stands in for nuScenes, a tiny model for the
preset), or is listed with the reason it cannot run here. A README command missing from
COMMANDS fails the test, so the README cannot grow an unchecked command."""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from odg_ros.commands import main as odg

ROOT = Path(__file__).resolve().parents[1]
TINY_MODEL = ["--set", "backbone=resnet18", "--set", "image_size=[64,176]", "--set",
              "num_frames=2", "--set", "embed_dims=64", "--set", "fpn_channels=64", "--set",
              "num_static=20", "--set", "num_dynamic=6", "--set", "ffn_dims=128", "--set",
              "points_per_layer=[1,2,2,4,4,8]", "--set", "mixing_out_points=8",
              "--workers", "0", "--render-pixels", "16", "--device", "cpu"]

RUN = "run"
COMMANDS = {
    "make demo": "3 minutes; the same path at tiny sizes is test/demo/test_demo.py",
    "make test": "the whole test suite",
    "odg_node --help": RUN,
    "odg_node --ros-args --params-file config/odg.yaml -p device:=cpu":
        "runs until stopped; its start-up with these defaults is test/ros/test_node_startup.py",
    "export FASTDDS_DEFAULT_PROFILES_FILE=$PWD/config/fastdds_localhost.xml "
    "ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT RMW_IMPLEMENTATION=rmw_fastrtps_cpp":
        "shell settings; test_the_readme_dds_settings_are_those_of_dds_py",
    "unset ROS_LOCALHOST_ONLY": "shell settings; test_the_readme_dds_settings_are_those_of_dds_py",
    "odg prepare --dataroot data/nuscenes --version v1.0-mini --split train --out "
    "data/nuscenes/infos_train.pkl": RUN,
    "odg prepare --dataroot data/nuscenes --version v1.0-mini --split val --out "
    "data/nuscenes/infos_val.pkl": RUN,
    "odg train --preset odg_t --data data/nuscenes/infos_train.pkl --out runs/odg_t "
    "--backbone-weights resnet50-0676ba61.pth --steps 2000": RUN,
    "odg eval --checkpoint runs/odg_t/final.pt --data data/nuscenes/infos_val.pkl --save-pred "
    "runs/odg_t/pred": RUN,
    "odg score --pred runs/odg_t/pred --data data/nuscenes/infos_val.pkl": RUN,
    "odg export --checkpoint runs/odg_t/final.pt --out runs/odg_t.pt --calibrate "
    "data/nuscenes/infos_train.pkl --limit 48": RUN,
    "torchrun --standalone --nproc_per_node 8 -m odg_ros.commands train --preset odg_t --data "
    "data/nuscenes/infos_train.pkl --out runs/odg_t --backbone-weights "
    "resnet50-0676ba61.pth": "needs GPUs; odg train under torchrun is test/train/test_train.py",
    "odg bag nuscenes --dataroot data/nuscenes --version v1.0-mini --scene scene-0061 --out "
    "bags/scene-0061": RUN,
    "odg replay bags/scene-0061 --clock": RUN,
    "python3 -m venv .venv": "the GPU install (a CUDA build of PyTorch from its registry)",
    ".venv/bin/pip install torch --index-url https://download.pytorch.org/whl/cu128":
        "the GPU install (a CUDA build of PyTorch from its registry)",
    "make setup": "part of make test / make demo",
    "rviz2 -d config/odg.rviz": "needs RViz; the file is checked by test_rviz_config",
    "cd ~/ws && git clone <this repo> src/odg_ros": "a ROS 2 workspace",
    "rosdep install --from-paths src src/odg_ros/msg -y --ignore-src": "needs a ROS 2 install",
    "colcon build --base-paths src src/odg_ros/msg": "needs a ROS 2 install",
    "source install/setup.bash": "needs a ROS 2 install",
    "ros2 launch odg_ros odg.launch.py": "needs a ROS 2 install",
}


def readme_commands() -> list[str]:
    """The commands of the README's bash blocks, continuation lines joined, comments cut."""
    text = (ROOT / "README.md").read_text()
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" #")[0].strip()
            if line and not line.startswith("#"):
                commands.append(" ".join(line.split()))
    return commands


def test_every_readme_command_is_checked_here():
    commands = readme_commands()
    assert set(commands) == set(COMMANDS), (
        f"in the README, not here: {sorted(set(commands) - set(COMMANDS))}; "
        f"here, not in the README: {sorted(set(COMMANDS) - set(commands))}")


def tiny(command: str, tmp: Path) -> list[str]:
    """A README command with its paths moved under tmp and its sizes made tiny."""
    command = (command.replace("data/nuscenes", str(tmp / "nuscenes"))
               .replace("runs/", f"{tmp}/runs/").replace("bags/", f"{tmp}/bags/")
               .replace("scene-0061", "scene-0001")
               .replace("resnet50-0676ba61.pth", str(tmp / "backbone.pth"))
               .replace("--steps 2000", "--steps 1"))
    argv = shlex.split(command)
    if argv[:2] == ["odg", "train"]:
        argv += TINY_MODEL
    if argv[:2] in (["odg", "eval"], ["odg", "export"]) and "--device" not in argv:
        argv += ["--device", "cpu"] if argv[1] == "eval" else []
    if argv[:2] == ["odg", "replay"]:
        argv += ["--quiet", "--rate", "20"]
    return argv


def test_the_readme_commands_run_at_tiny_sizes(tmp_path, capsys):
    import torch
    from testing.helpers import tiny_config
    from odg_ros.network import ODG

    # nuScenes v1.0-mini stands in: a synthetic world in that layout (4 scenes: one is val)
    assert odg(["synth", "--out", str(tmp_path / "nuscenes"), "--scenes", "4", "--seconds",
                "0.5", "--image-size", "36", "64", "--version", "v1.0-mini"]) == 0
    # a torchvision-layout backbone file for the tiny model's ResNet-18
    torch.save(ODG(tiny_config()).backbone.state_dict(), tmp_path / "backbone.pth")
    ran = []
    for command in readme_commands():
        if COMMANDS[command] != RUN:
            continue
        argv = tiny(command, tmp_path)
        if argv[0] == "odg_node":
            pytest.importorskip("rclpy", reason="odg_node --help imports rclpy")
            from odg_ros.ros.node import main as node_main
            assert node_main(argv) == 0, command
            assert "parameters" in capsys.readouterr().out
        elif argv[:2] == ["odg", "replay"]:
            pytest.importorskip("rclpy", reason="odg replay needs rclpy")
            result = subprocess.run([sys.executable, "-m", "odg_ros.commands", *argv[1:]],
                                    capture_output=True, text=True, timeout=120,
                                    env=dict(os.environ, PYTHONPATH=str(ROOT)))
            assert result.returncode == 0, (command, result.stderr[-2000:])
        else:
            assert odg(argv[1:]) == 0, (command, capsys.readouterr().err[-2000:])
        ran.append(command)
    assert len(ran) == sum(v == RUN for v in COMMANDS.values())


def test_the_readme_dds_settings_are_those_of_dds_py():
    """What the README tells a user to set for a node started by hand is what
    odg_ros.ros.dds sets for the demo, odg replay and the tests."""
    from odg_ros.ros.dds import localhost_dds_env
    commands = readme_commands()
    export = next(c for c in commands if c.startswith("export "))
    readme = dict(item.split("=", 1) for item in export.split()[1:])
    readme["FASTDDS_DEFAULT_PROFILES_FILE"] = readme["FASTDDS_DEFAULT_PROFILES_FILE"].replace(
        "$PWD", str(ROOT))
    env = localhost_dds_env({"ROS_LOCALHOST_ONLY": "1", "HOME": "/home/someone"})
    assert readme == {k: v for k, v in env.items() if k != "HOME"}
    assert "unset ROS_LOCALHOST_ONLY" in commands and "ROS_LOCALHOST_ONLY" not in env


def test_rviz_config_shows_the_node_outputs():
    from odg_ros.online.parameters import load_schema
    config = yaml.safe_load((ROOT / "config/odg.rviz").read_text())["Visualization Manager"]
    topics = {d["Class"].split("/")[-1]: d["Topic"]["Value"]
              for d in config["Displays"] if "Topic" in d}
    assert topics == {"PointCloud2": "/odg_node/occupancy/cloud",
                      "Map": "/odg_node/occupancy/bev",
                      "MarkerArray": "/odg_node/objects/markers"}
    assert config["Global Options"]["Fixed Frame"] == load_schema()["base_frame"].default
    node_source = (ROOT / "odg_ros/ros/output_messages.py").read_text()      # the node's Outputs
    for topic in topics.values():
        assert f'"~/{topic.removeprefix("/odg_node/")}"' in node_source, topic
