"""tools/gpu_checks.sh, the one command a GPU machine runs: checked here on the CPU stand-in
(DEVICE=cpu), whose commands are those of the GPU run with the device swapped."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def gpu_checks(part, out, **env):
    return subprocess.run(["bash", str(ROOT / "tools/gpu_checks.sh"), part, str(out)],
                          env=dict(os.environ, PYTHON=sys.executable, **env),
                          capture_output=True, text=True, timeout=300)


def test_build_part_describes_the_machine(tmp_path):
    result = gpu_checks("build", tmp_path, DEVICE="cpu")
    assert result.returncode == 0, result.stdout + result.stderr
    machine = json.loads((tmp_path / "machine.json").read_text())
    assert machine["torch"] == torch.__version__
    assert machine["device"] is None and machine["gsplat"] == "1.5.3"


def test_without_a_gpu_the_cuda_run_says_so(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    result = gpu_checks("build", tmp_path, DEVICE="cuda")
    assert result.returncode == 2
    assert "no CUDA device for PyTorch here" in result.stdout


def test_an_unknown_part_is_refused(tmp_path):
    result = gpu_checks("benchmark", tmp_path, DEVICE="cpu")
    assert result.returncode == 2
    assert "unknown part 'benchmark'" in result.stdout
