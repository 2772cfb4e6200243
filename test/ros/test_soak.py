"""The soak tool end to end, short (the hour-long run is a benchmark, docs/node.md): `odg
soak` loops two synthetic scenes of different kinds into a real odg_node process (a tiny
model) for a minute at 1x and half a minute at 4x, and its report holds the invariants,
not performance numbers (a slow 2-core machine must pass): the node ran, no ERROR status,
every history reset explained (new scenes, or outputs further apart than
history_max_gap), every new scene restarted the history, memory sampled throughout, a
latency for the outputs, and at 1x no input refused and every completed set published or
dropped as stale. (At 4x a slow machine's node cannot take every message in: some sets are
refused, e.g. pose misses, which the report shows.)"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from odg_ros.bench.soak_report import TARGET_RESTART_S, TARGET_RSS_GROWTH_MB
from odg_ros.online.errors import BAD_INPUT_KINDS
from testing.helpers import write_tiny_checkpoint


# "no output for 5 s" is the node's honest ERROR when a shared machine starves it for that
# long (seen at a load average of 15 on 2 cores: steps of up to 10 s); here any ERROR is to
# mean a fault, so that timeout is beyond such stalls. The hour-long soak keeps the default.
TOLERANT = ("-p", "no_output_timeout:=30.0")


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    from odg_ros.bench.soak_report import synthetic_scenes
    return synthetic_scenes(tmp_path_factory.mktemp("soak_scenes"), seconds=3,
                            image_hw=(45, 80), kinds=(("normal", "city"),
                                                      ("quiet", "open-road")),
                            progress=False)


def test_a_short_soak_at_1x_and_4x(scenes, rclpy_module, tmp_path):
    checkpoint = write_tiny_checkpoint(tmp_path / "tiny.pt")
    result = subprocess.run(
        [sys.executable, "-m", "odg_ros.commands", "soak", *map(str, scenes),
         "--run", "1", "1", "--run", "4", "0.5", "-p", f"checkpoint:={checkpoint}",
         "-p", "device:=cpu", *TOLERANT, "--out", str(tmp_path / "report"), "--logs",
         str(tmp_path / "logs"), "--quiet", "--domain-id", os.environ["ROS_DOMAIN_ID"]],
        capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    written = sorted(p.suffix for p in (tmp_path / "report").iterdir())
    assert written == [".json", ".md", ".png"], written
    document = json.loads(next((tmp_path / "report").glob("*.json")).read_text())
    assert "# Soak: odg_node" in next((tmp_path / "report").glob("*.md")).read_text()
    one, four = document["runs"]
    for run in (one, four):
        context = (run["rate"], run["resets"], run["statuses"], result.stdout[-2000:])
        assert not run["crashed"] and run["statuses"]["error"] == 0, context
        assert run["resets"]["unexpected"] == [], context
        assert run["resets"]["new_scenes_without_reset"] == 0, context
        assert run["outputs"] >= 3 and run["outputs_received"] >= run["outputs"] - 1, context
        assert run["latency_ms_wall"]["p50"] is not None
        assert run["processing_ms"]["p50"] is not None
    assert one["resets"]["at_scene_changes"] >= 3       # scenes of 3 s for a minute
    assert one["inputs_refused"] == {}, one["inputs_refused"]
    # every completed set was published or dropped as stale (a few may still be waiting or
    # in the model as the node stops)
    assert 0 <= one["sets_completed"] - one["outputs"] - one["stale_sets_dropped"] <= 3, one
    assert one["rss"]["samples"] >= 40 and one["rss"]["peak_mb"] > 50
    # the hour's bound, over the minute's second half
    assert one["rss"]["growth_after_warmup_mb"] <= TARGET_RSS_GROWTH_MB, one["rss"]
    print({r["rate"]: (r["rss"], r["latency_ms_wall"], r["resets"]["at_scene_changes"],
                       r["outputs"], r["sets_completed"]) for r in (one, four)})
    assert set(four["inputs_refused"]) <= set(BAD_INPUT_KINDS)
    # the records, kept with the logs, give the same report again
    records = next((tmp_path / "logs").glob("*-soak-records.json"))
    again = subprocess.run([sys.executable, "-m", "odg_ros.commands", "soak", "--from-json",
                            str(records), "--out", str(tmp_path / "again")],
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stderr[-3000:]
    assert json.loads(next((tmp_path / "again").glob("*.json")).read_text())["runs"] == \
        document["runs"]


def test_the_node_killed_mid_bag_and_started_again(scenes, rclpy_module, tmp_path):
    """SIGKILL twice while the scenes play at 1x: each new process publishes again, none
    of its outputs is made of an image from before it started (a new process holds no
    history: every frame it uses came after), no ERROR status. The time to the first output
    is the shipped model's figure in a benchmark (docs/node.md); here it is only bounded."""
    checkpoint = write_tiny_checkpoint(tmp_path / "tiny.pt")
    result = subprocess.run(
        [sys.executable, "-m", "odg_ros.commands", "soak", *map(str, scenes),
         "--restarts", "2", "-p", f"checkpoint:={checkpoint}", "-p", "device:=cpu", *TOLERANT,
         "--out", str(tmp_path / "report"), "--logs", str(tmp_path / "logs"), "--quiet",
         "--domain-id", os.environ["ROS_DOMAIN_ID"]],
        capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    document = json.loads(next((tmp_path / "report").glob("*.json")).read_text())
    restarts = document["restarts"]["restarts"]
    print(restarts)
    assert len(restarts) == 2, document["restarts"]
    for restart in restarts:
        assert restart["outputs"] >= 1 and restart["stale_outputs"] == 0, restart
        assert restart["outputs_not_checked"] < restart["outputs"], restart
        assert restart["errors"] == 0, restart
        # up (its first report: Python, torch and the model loaded) -> its first output:
        # the node's own recovery, within the target; the start-up before it is the
        # machine's (4 s of imports alone on 2 busy shared cores)
        # (its first output may come before its first report: one a diagnostics period)
        assert 0 < restart["up_after_s"] < 60 and 0 < restart["first_output_after_s"] < 60, \
            restart
        assert restart["first_output_after_s"] - restart["up_after_s"] <= \
            TARGET_RESTART_S, restart
