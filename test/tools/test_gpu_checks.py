"""tools/gpu_checks.sh, the one command a GPU machine runs: checked here on the CPU stand-in
(DEVICE=cpu), whose commands are those of the GPU run with the device swapped."""
import json
import os
import subprocess
import sys

import pytest
import torch

from testing import REPOSITORY

ROOT = REPOSITORY


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
                     "tools.measure_node_overhead --sets", "pytest -q"):
        assert expected in commands, expected
    train = [line for line in lines if line[:2] == ["odg", "train"] and "odg_t" in line]
    assert train and all("--backbone-weights" in line for line in train)
    bench = [line for line in lines if line[:2] == ["odg", "bench"] and "--compile" in line]
    assert any("eager,compiled,graphs" in line and "fp32,bf16" in line for line in bench)
    assert "command lines, 0 refused" in result.stdout


def first_part(tmp_path, script=None):
    """CHECK=parse of the first part (of ``script``, a changed copy of the script if given)
    -> (the result, the recorded lines)."""
    command = ["bash", str(ROOT / "tools/gpu_checks.sh")]
    if script is not None:
        changed = tmp_path / "gpu_checks.sh"
        changed.write_text(script.replace('cd "$(dirname "$0")/.."', f'cd "{ROOT}"'))
        command = ["bash", str(changed)]
    out = tmp_path / "out"
    result = subprocess.run(command + ["first", str(out)],
                            env=dict(os.environ, PYTHON=sys.executable, DEVICE="cpu",
                                     CHECK="parse"),
                            capture_output=True, text=True, timeout=300)
    lines = [json.loads(line) for line in (out / "commands.jsonl").read_text().splitlines()]
    return result, lines, out


def test_the_first_part_is_one_bounded_call_of_what_is_new(tmp_path):
    """``first``: the query budgets replayed as CUDA graphs (ODG-T and ODG-L), the training
    step at the size users train (batch 1 and 4: waits and seconds), FlexAttention at ODG-T's
    and ODG-L's sizes, ODG-T's node step compiled into one graph; nothing that runs on the
    CPU only, no gsplat build. The check adds up the time limits of its checks: at most
    7 minutes, and at most 8 files come back."""
    result, lines, out = first_part(tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    commands = [line for line in lines if line[0] not in ("bound", "limit")]
    budgets = [line for line in commands if line[0] == "tools.budget_graphs"]
    assert len(budgets) == 1 and budgets[0][budgets[0].index("--preset") + 1:][:2] == \
        ["odg_t", "odg_l"]
    waits = [line for line in commands if line[0] == "tools.sync_debug_step"]
    assert len(waits) == 1 and "--no-cpu-census" in waits[0]
    assert waits[0][waits[0].index("--batch-size") + 1:][:2] == ["1", "4"]
    assert waits[0][waits[0].index("--image-size") + 1:][:2] == ["256", "704"]
    flex = [line for line in commands if line[0] == "tools.flex_attention_check"]
    assert flex[0][flex[0].index("--queries") + 1:][:2] == ["600", "4800"]
    bench = [line for line in commands if line[:2] == ["odg", "bench"]]
    assert len(bench) == 1 and "eager,graphs" in bench[0] and "odg_t" in bench[0]
    assert not [line for line in commands if line[0] == "pytest"]      # no CPU-only test
    assert "gsplat CUDA kernels" not in result.stdout
    limit = [line for line in lines if line[0] == "limit"]
    assert limit == [["limit", "first", "420", "8", limit[0][4]]] and int(limit[0][4]) <= 8
    assert "part first: 8 time limits, wall time at most 420 s" in result.stdout
    assert {p.name for p in out.iterdir()} == {"commands.jsonl", "gpu_checks.log",
                                               "first.tar.gz", "summary.md", "summary.json"}


def test_first_checks_that_do_not_fit_fail_the_parse_check(tmp_path):
    """Planted: a check's limit raised past the part's 420 s."""
    script = (ROOT / "tools/gpu_checks.sh").read_text()
    assert 'bounded "training step, batch 1 and 4" 90 ' in script
    result, _, _ = first_part(tmp_path, script.replace(
        'bounded "training step, batch 1 and 4" 90 ', 'bounded "training step, batch 1 and 4" 150 '))
    assert result.returncode == 1
    assert "part first: its checks need 454 s, more than its 420 s" in result.stdout


def test_first_summary_gives_the_figures_against_their_targets(tmp_path):
    """tools/gpu_report.py --first on what the checks write: the node step's FPS, the decoder
    at auto against full, the training step's seconds and waits, FlexAttention's errors."""
    from tools.gpu_report import first_figures, first_summary
    (tmp_path / "checks.jsonl").write_text(
        json.dumps({"check": "machine", "status": "ok", "seconds": "3", "limit": "10"}) + "\n"
        + json.dumps({"check": "node step", "status": "skipped (no time left)",
                      "seconds": "0", "limit": "90"}) + "\n")
    (tmp_path / "budgets.json").write_text(json.dumps([{
        "preset": "odg_l", "predictors": {
            "full": {"budgets": ["full"], "captures": 1, "grid_agreement_min": 1.0,
                     "step_ms": {"full": 20.0}},
            "auto": {"budgets": ["s4000-d800", "s2400-d400", "s1400-d200"], "captures": 3,
                     "grid_agreement_min": 0.9999, "step_ms": {"s4000-d800": 20.5}}},
        "decoder_ms": {"full": 12.0, "s4000-d800": 12.2},
        "open_road": {"speedup": 1.6, "full_decoder_ms": 12.0, "auto_decoder_ms": 7.5,
                      "refined": 0.56}}]))
    (tmp_path / "training_step.json").write_text(json.dumps([{
        "preset": "odg_t", "image_size": [256, 704], "frames": 8, "batch_size": 4,
        "seconds_per_sample": 0.25, "sync_debug_waits": 7, "census_cuda_waits": 7.0}]))
    (tmp_path / "flex_attention.json").write_text(json.dumps({"tolerance": 5e-3, "sizes": [{
        "queries": 4800, "compile_s": 20.0, "flex_error": 2e-3, "sdpa_error": 2.1e-3,
        "flex_ms": 0.5, "sdpa_ms": 3.0, "flex_peak_mib": 10.0, "sdpa_peak_mib": 700.0}]}))
    (tmp_path / "node_step.json").write_text("{cut off")
    figures = first_figures(tmp_path)
    text = first_summary(figures)
    assert "| node step | skipped (no time left) | 0 | 90 |" in text
    assert "| odg_l decoder: full / auto on the open road | 1.60 | >= 1.5 (ODG-L) |" in text
    assert "| odg_l step, full budget, graphs of the eager step | 50.0 |" in text
    assert "| training step odg_t 256 x 704, 8 frames, batch 4 | 0.250 | s per sample | " \
           "host waits: sync-debug 7, census 7 (target <= 8) |" in text
    assert "| odg_l | auto | 3 | s4000-d800, s2400-d400, s1400-d200 | 0.9999 |" in text
    assert "| 4800 | 20.0 | 2.0e-03 | 2.1e-03 | 0.5 | 3.0 |" in text
    assert "(not summarised: node_step.json:" in text
    assert json.loads(json.dumps(figures))["targets"]["open_road_decoder_speedup"] == 1.5


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


def test_report_tables_from_the_results_of_a_run(tmp_path):
    """tools/gpu_report.py: training seconds after the warm-up steps, samples/s from the batch
    in the run's name, GPU utilisation, the profile and a real node bench result."""
    from tools.gpu_report import report
    from odg_ros.bench.step_timing import bench_node_step
    from testing.online import make_model

    model, cfg = make_model()
    bench = bench_node_step(cfg, "cpu", ("eager",), iters=1, warmup=0, model=model,
                            progress=False, precisions=("fp32", "bf16"))
    (tmp_path / "node_tiny.json").write_text(json.dumps(bench))
    (tmp_path / "bench.json").write_text(json.dumps({"tiny-fp32": bench}))
    seconds = [9.0] * 4 + [0.5, 0.7, 0.6, 0.6, 0.8, 0.8, 0.8, 0.8]   # one read every 4 steps
    rows = ["step,seconds,skipped_total"] + [f"{i + 1},{s},0" for i, s in enumerate(seconds)]
    (tmp_path / "train_odg_t_b4.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "gpu_util_speed.csv").write_text(
        "timestamp, utilization.gpu [%], memory.used [MiB], power.draw [W]\n"
        "2026/11/25 10:00:00.000, 0, 1024, 70\n2026/11/25 10:00:00.200, 80, 4096, 300\n"
        "2026/11/25 10:00:00.400, 100, 2048, 310\n2026/11/25 10:00:00.6")   # cut off
    (tmp_path / "profile_odg_t.json").write_text(json.dumps({
        "preset": "odg_t", "image_size": [256, 704], "device": "cuda:0", "ops_per_step": 9000.0,
        "syncs_per_step": 40.0, "by_phase": {"forward": {"ops": 5000.0, "syncs": 2.0}},
        "gpu": {"wall_s": 0.5, "kernel_s": 0.4, "busy": 0.8,
                "top_kernels": [{"name": "sm90_gemm", "calls": 300, "seconds": 0.1}]}}))
    (tmp_path / "demo.json").write_text("{not json")
    (tmp_path / "sync_debug_b4.json").write_text(json.dumps({
        "preset": "odg_t", "image_size": [32, 88], "frames": 2, "batch_size": 4,
        "sync_debug_waits": 7, "sync_debug_lines": {"losses/box.py:120": 1, "x.py:1": 6},
        "census_cuda_waits": 6.0, "census_cuda_paths_waits": 6.0, "census_cuda_paths_ops": 9000.0,
        "census_cuda_paths_lines": {"losses/box.py:120": 1, "x.py:1": 5}}))
    (tmp_path / "backbone.json").write_text(json.dumps({
        "preset": "odg_t", "precision": "bf16", "input": [6, 3, 256, 704], "device": "H100",
        "ms": {"eager": {"ours": 2.0, "reference NCHW": 4.0, "reference channels-last": 2.5,
                         "ours / fastest reference": 0.8},
               "graph": {"ours": 1.2, "reference NCHW": 3.0, "reference channels-last": 1.0,
                         "ours / fastest reference": 1.2}}}))
    text = report(tmp_path)
    assert "| odg_t 32 x 88, 2 frames | 4 | 7 | 6 | 6 | 9,000 | no |" in text
    assert "| 4 | x.py:1 | 6 | 5 |" in text and "| 4 | losses/box.py:120 |" not in text
    assert "| graph | 1.200 | 3.000 | 1.000 | 1.200 |" in text
    # median of the steps after the first 4: 0.75 s a step of 4 samples
    assert "| odg_t_b4 | 12 | 4 | 0.750 | 0.188 | 5.33 | 36.0 s | 0 skipped |" in text
    assert "| speed | 3 | 60 | 90 | 4.0 |" in text
    assert "| odg_t | 256 x 704 | cuda:0 | 9,000 | 40 | 0.500 | 0.400 | 80 |" in text
    assert "| odg_t | sm90_gemm | 300 | 100.0 |" in text
    for variant in ("eager-fp32", "eager-bf16"):
        assert f"| tiny | {variant} | {cfg.image_size[0]} x {cfg.image_size[1]} |" in text
    assert "| tiny | eager-bf16 | " in text.split("Largest differences")[1]
    assert "(not summarised: demo.json: JSONDecodeError" in text
    assert f"| tiny-fp32 (eager-fp32) | {cfg.image_size[0]} x {cfg.image_size[1]} |" in text


def test_report_tables_of_the_first_h100_run_give_its_numbers():
    """The committed results of the first H100 run give the numbers its report states."""
    from tools.gpu_report import report
    text = report(ROOT / "docs/reports/2026-11-25-h100", skip_steps=2)   # "from step 3 on"
    assert "| odg_t_torch | 12 | 1 | 2.976 |" in text and "| odg_cpu_torch | 12 | 1 | 1.421 |" in text
    assert "| odg_t-fp32 | 256 x 704 | 8 | 14.2 | 70.2 (11.4 / 56.0 / 2.5) | 1.5 |" in text
    assert "| cuda | 26.46 | 33.25 | 52.93 | 18.54 |" in text
    assert "| tests_first_run.xml | 46 | 1 | 0 | test_trains_on_cuda_with_the_gsplat_renderer |" in text
