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


def test_every_command_line_of_every_part_parses(tmp_path):
    """CHECK=parse records each command of the GPU run (CUDA modes included) and has each
    command's own parser check it, and pytest collect the tests: no typo reaches a GPU."""
    result = gpu_checks("all", tmp_path, DEVICE="cpu", CHECK="parse")
    assert result.returncode == 0, result.stdout + result.stderr
    lines = [json.loads(line) for line in (tmp_path / "commands.jsonl").read_text().splitlines()]
    commands = {" ".join(line[:2]) for line in lines}
    for expected in ("odg train", "odg profile", "odg bench", "odg export", "odg demo",
                     "tools/measure_node_overhead.py --sets", "pytest -q"):
        assert expected in commands, expected
    train = [line for line in lines if line[:2] == ["odg", "train"] and "odg_t" in line]
    assert train and all("--backbone-weights" in line for line in train)
    bench = [line for line in lines if line[:2] == ["odg", "bench"] and "--compile" in line]
    assert bench and "eager,compiled,graphs" in bench[0] and "fp32,bf16" in bench[0]
    assert "29 command lines, 0 refused" in result.stdout


def test_a_typo_in_a_command_line_fails_the_parse_check(tmp_path):
    script = (ROOT / "tools/gpu_checks.sh").read_text()
    broken = tmp_path / "gpu_checks.sh"
    broken.write_text(script.replace("--log-every 4", "--log-evry 4")
                      .replace('cd "$(dirname "$0")/.."', f'cd "{ROOT}"'))
    result = subprocess.run(["bash", str(broken), "speed", str(tmp_path / "out")],
                            env=dict(os.environ, PYTHON=sys.executable, DEVICE="cpu",
                                     CHECK="parse"),
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 1
    assert "unrecognized arguments: --log-evry" in result.stdout
