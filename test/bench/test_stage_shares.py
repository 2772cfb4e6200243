"""The stages' shares of the node's step (bench/stage_shares.py): by the step's marks and by
the step without the stage, from one run, agree on a stage of known cost."""
import time

import pytest

from odg_ros.bench.stage_shares import format_shares, stage_shares
from odg_ros.bench.step_timing import node_settings
from odg_ros.network.visibility import Visibility
from testing.online import make_model, make_sets

BURN_MS = 100.0


def burning(forward):
    """``forward`` after BURN_MS of this thread's CPU time: a visibility of known cost."""
    def burn_then_forward(self, *args, **kwargs):
        end = time.thread_time() + BURN_MS / 1e3
        while time.thread_time() < end:
            pass
        return forward(self, *args, **kwargs)
    return burn_then_forward


def test_marks_and_difference_agree_on_a_stage_of_known_cost(monkeypatch):
    monkeypatch.setattr(Visibility, "forward", burning(Visibility.forward))
    model, cfg = make_model()
    sets = make_sets(cfg, 7)
    result = stage_shares(model, cfg, sets, node_settings(precision="fp32"), progress=False)
    assert result["threads"] == 1 and result["sets"] == 5 and result["mode"] == "eager"
    assert set(result["by_marks"]) == set(result["by_difference"]) == {"padding",
                                                                        "visibility"}
    # the burnt CPU time shows in the visibility's marks and in what its absence saves
    step = result["step_cpu_ms"]
    assert result["stage_cpu_ms"]["visibility"] >= BURN_MS
    assert result["step_cpu_ms"] - result["without_cpu_ms"]["visibility"] >= 0.8 * BURN_MS
    marks, difference = result["by_marks"]["visibility"], result["by_difference"]["visibility"]
    assert BURN_MS / step <= marks < 1 and difference > 0.8 * BURN_MS / step
    assert abs(marks - difference) < 0.12, result
    assert 0 <= result["by_marks"]["padding"] < 0.2
    assert "visibility" in format_shares(result) and "padding" in format_shares(result)


def test_a_stage_switched_off_in_the_settings_cannot_be_measured():
    model, cfg = make_model()
    with pytest.raises(ValueError, match="visibility off"):
        stage_shares(model, cfg, make_sets(cfg, 3), node_settings(visibility=False),
                     progress=False)
    with pytest.raises(ValueError, match="does not pad"):
        stage_shares(model, cfg.replace(occupancy_padding=False), make_sets(cfg, 3),
                     progress=False)


def test_odg_bench_shares_prints_both_measures(tmp_path, capsys):
    import json
    from odg_ros.commands import main
    from testing.helpers import write_tiny_checkpoint
    checkpoint = write_tiny_checkpoint(tmp_path / "tiny.pt")
    assert main(["bench", "--shares", "--checkpoint", str(checkpoint), "--iters", "2",
                 "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["sets"] == 2 and result["threads"] == 1 and result["inputs"] == "random"
    assert set(result["by_marks"]) == set(result["by_difference"])
    assert "visibility" in result["by_marks"]
    assert main(["bench", "--shares", "--no-visibility", "--checkpoint",
                 str(checkpoint)]) != 0
