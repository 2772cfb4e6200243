"""``odg ... --set`` goes through the node's own validator (types, misspelt booleans,
ranges, unknown keys), and a damaged or foreign bag: each is one line,
``odg CMD: error: ...``, exit code 2, no traceback. A bag cut short (a recording that ended
badly) plays up to the damage after one warning line; a missing one is "not found"."""
from __future__ import annotations

import pickle
import shutil

import pytest
import torch

from odg_ros.commands import main
from odg_ros.online.parameters import load_schema, model_settings, parse_settings


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("settings")
    infos = {"version": "v1.0-trainval", "dataset": "nuscenes", "dataroot": str(root),
             "infos": [{"token": "k0"}]}
    (root / "infos.pkl").write_bytes(pickle.dumps(infos))
    torch.save({"weights": [1, 2]}, root / "foreign.pt")
    return {"root": str(root), "infos": str(root / "infos.pkl"),
            "checkpoint": str(root / "foreign.pt")}


SET_CASES = {   # --set item: what the one line says
    "score_threshold=abc": "--set score_threshold='abc': expected float",
    "motion_compensation=flase": "--set motion_compensation='flase': expected bool",
    "occupancy_padding=yes please": "--set occupancy_padding='yes please': expected bool",
    "score_threshold=2": "--set score_threshold=2.0: expected -1 to 1",
    "box_score_threshold=-3": "expected -1 to 1",
    "num_frames=2.5": "--set num_frames=2.5: expected int",
    "image_size=[128, x]": "expected a list of ints",
    "scor_threshold=0.3": "--set scor_threshold: not a model setting; did you mean "
                          "score_threshold?",
    "score_threshold": "--set expects KEY=VALUE",
}


@pytest.mark.parametrize("item", SET_CASES)
@pytest.mark.parametrize("command", ["eval", "train"])
def test_a_bad_setting_is_one_line_and_exit_code_2(item, command, files, capsys):
    argv = {"eval": ["eval", "--checkpoint", files["checkpoint"], "--data", files["infos"]],
            "train": ["train", "--data", files["infos"], "--out", files["root"] + "/run"]}
    assert main([*argv[command], "--set", item]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"odg {command}: error: "), err
    assert SET_CASES[item] in lines[0], err


def test_the_settings_share_the_node_schemas_rules():
    schema, rules = load_schema(), model_settings()
    for name in ("score_threshold", "box_score_threshold"):
        assert rules[name] == schema[name]
    assert parse_settings(["occupancy_padding=false", "score_threshold=0.4",
                           "image_size=[128, 352]"]) == {
        "occupancy_padding": False, "score_threshold": 0.4, "image_size": [128, 352]}
    # a negative threshold keeps the checkpoint's own, as the node's parameter does
    from odg_ros.commands.common import config_overrides
    assert config_overrides(["score_threshold=-1", "das_attention=false"]) == {
        "das_attention": False}


@pytest.fixture(scope="module")
def good_bag(tmp_path_factory):
    from odg_ros.bags.nuscenes_source import NuScenesSensorTables
    from odg_ros.bags.writer import write_scene_bag
    from testing import tiny_nuscenes
    root = tmp_path_factory.mktemp("tiny_nuscenes")
    tiny_nuscenes.build(root, scene_durations_s=(1.0,))
    out = tmp_path_factory.mktemp("bags") / "scene-0001"
    write_scene_bag(NuScenesSensorTables(root).scene_records("scene-0001"), out,
                    progress=False)
    return out


def damaged(good_bag, tmp_path, how):
    bag = tmp_path / how
    shutil.copytree(good_bag, bag)
    mcap = next(bag.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    if how == "truncated":                      # a copy cut short
        mcap.write_bytes(bytes(data[:len(data) // 2]))
    elif how == "corrupt":                      # a chunk overwritten, ends intact
        data[len(data) // 3:len(data) // 3 + 5000] = b"\xab" * 5000
        mcap.write_bytes(bytes(data))
    elif how == "foreign":                      # some other metadata.yaml
        (bag / "metadata.yaml").write_text("hello: world\n")
    return bag


@pytest.mark.parametrize("how", ["corrupt", "foreign"])
def test_a_damaged_or_foreign_bag_is_one_line(how, good_bag, tmp_path, capsys):
    pytest.importorskip("rclpy", reason="odg replay publishes with rclpy")
    from odg_ros.ros.dds import use_localhost_dds
    use_localhost_dds()
    bag = damaged(good_bag, tmp_path, how)
    assert main(["replay", str(bag), "--quiet", "--rate", "50"]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("odg replay: error: "), err
    assert f"{bag} is not a readable rosbag2 bag" in lines[0]


def test_a_bag_cut_short_plays_to_the_damage_with_one_warning(good_bag, tmp_path, capsys):
    pytest.importorskip("rclpy", reason="odg replay publishes with rclpy")
    from odg_ros.ros.dds import use_localhost_dds
    use_localhost_dds()
    bag = damaged(good_bag, tmp_path, "truncated")      # cut mid-chunk: nothing complete
    assert main(["replay", str(bag), "--quiet", "--rate", "50"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"odg replay: error: {bag} ended badly")
    assert lines[0].endswith("not one message is complete")
    mcap = next(bag.glob("*.mcap"))                     # cut in the summary: every message
    mcap.write_bytes(next(good_bag.glob("*.mcap")).read_bytes()[:-100])
    assert main(["replay", str(bag), "--quiet", "--rate", "50"]) == 0
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"odg replay: warning: {bag} ended badly"), err
    assert "replaying the 376 of 376 messages before that, 1.04 s of bag time" in lines[0]
    assert out.startswith("published 376 messages")


def test_a_missing_bag_is_not_found(tmp_path, capsys):
    assert main(["replay", str(tmp_path / "nowhere"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"odg replay: error: {tmp_path / 'nowhere'} not found"
