"""The core-scaling probe (bench/core_scaling.py): its child process measures, the caller's
torch threads stay as they were, and a failing child is a one-line error."""
import subprocess

import pytest
import torch

from odg_ros.bench import core_scaling as probe


def test_one_thread_against_itself_scales_about_one_and_leaves_the_caller_alone():
    threads_before = torch.get_num_threads()
    result = probe.core_scaling(threads=1, size=256, repeats=3)
    assert torch.get_num_threads() == threads_before
    assert result["threads"] == 1 and result["one_thread_ms"] > 0 and result["threads_ms"] > 0
    # the same work twice: equal up to this shared machine's noise, never a factor of 2
    assert 0.5 < result["scaling"] < 2.0


def test_the_ratio_is_one_thread_over_all_threads(monkeypatch):
    def fake_run(command, **kwargs):
        assert command[-1] == "2"                      # asked for two threads
        return subprocess.CompletedProcess(command, 0, stdout='{"1": 0.03, "2": 0.016}\n',
                                           stderr="")
    monkeypatch.setattr(probe.subprocess, "run", fake_run)
    result = probe.core_scaling(threads=2)
    assert result == {"threads": 2, "one_thread_ms": 30.0, "threads_ms": 16.0,
                      "scaling": 1.88}
    line = probe.format_scaling(result, {**result, "scaling": 1.1})
    assert "1.88x" in line and "1.10x after" in line


def test_a_failing_probe_is_one_clear_error(monkeypatch):
    monkeypatch.setattr(probe, "_CHILD", "raise SystemExit('no torch here')")
    with pytest.raises(RuntimeError, match="core-scaling probe failed: no torch here"):
        probe.core_scaling(threads=1)
