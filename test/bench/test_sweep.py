"""``odg bench --sweep`` (odg_ros/bench/sweep.py): the Pareto front on hand-made numbers,
query budgets, the plots' axes, and a whole sweep of a tiny random-weights checkpoint on a
tiny hand-made world (JSON keys, PNG, scores equal to ``evaluate``)."""
import json

import numpy as np
import pytest
import torch

from odg_ros.bench.plots import axis_limits
from odg_ros.network import ODG
from odg_ros.network.checkpoint import load_model
from odg_ros.data.dataset import OccDataset
from odg_ros.bench.sweep import (SweepConfig, pareto_front, prepare_model, query_budget,
                                 quiet_and_busy, run_sweep, sample_camera_sets, select_configs,
                                 spread_indices)
from odg_ros.train.evaluate import evaluate

from testing.helpers import tiny_config, write_tiny_checkpoint, write_tiny_split


def tiny_cfg():
    return tiny_config(image_size=(32, 88), num_frames=3)


# ------------------------------------------------------------------------ pure functions
def test_pareto_front_on_hand_made_points():
    points = [(1.0, 5.0), (2.0, 4.0), (3.0, 4.0), (0.5, 6.0), (2.0, 1.0), (3.0, 4.0),
              (9.0, None), (4.0, float("nan")), (0.4, 6.0)]
    # (2, 4) is beaten by (3, 4); (2, 1) by everything to its right; (0.4, 6) by (0.5, 6);
    # the two equal (3, 4) both stay; None / NaN are out; sorted by FPS
    assert pareto_front(points) == [3, 0, 2, 5]
    assert pareto_front([]) == []
    assert pareto_front([(1.0, 1.0)]) == [0]
    # a slower path with 3e-4 more mIoU (float noise) is on the exact front, not on the
    # front within a tolerance; nor with 3e-3 across a rounding boundary (10.163 / 10.166:
    # the sweep of 2026-11-21, which 2-decimal rounding kept on the front)
    noisy = [(4.17, 8.7142), (3.36, 8.7145)]
    assert pareto_front(noisy) == [1, 0]
    assert pareto_front(noisy, tolerance=0.02) == [0]
    assert pareto_front([(3.65, 10.1627), (2.86, 10.1660)], tolerance=0.02) == [0]
    # more than the tolerance better: both stay; within it, the faster one alone
    assert pareto_front([(5.5, 10.15), (3.65, 10.20)], tolerance=0.02) == [1, 0]
    assert pareto_front([(5.5, 10.151), (3.65, 10.163)], tolerance=0.02) == [0]


def test_samples_are_spread_over_the_split():
    assert spread_indices(100, 5) == [0, 25, 50, 74, 99]
    assert spread_indices(3, 8) == [0, 1, 2]
    assert spread_indices(10, 1) == [0]


def test_quiet_and_busy_quarters():
    load = [{"index": i, "has_occ": True, "occupied_camera": v, "boxes": b}
            for i, (v, b) in enumerate([(50, 1), (10, 9), (30, 2), (90, 0), (10, 1), (70, 5),
                                        (20, 3), (60, 1)])]
    load.append({"index": 8, "has_occ": False, "occupied_camera": 0, "boxes": 0})
    quiet, busy = quiet_and_busy(load)
    assert quiet == [4, 1] and busy == [5, 3]          # ties on voxels: fewer boxes first
    assert quiet_and_busy(load[:1]) == ([0], [0])
    assert quiet_and_busy([]) == ([], [])


def test_select_configs_by_name_and_from_json(tmp_path):
    defaults = select_configs(None, 4)
    names = [c.name for c in defaults]
    assert names[:3] == ["full-h4", "full-h1", "full-h2"]
    assert {"q50-h4", "q25-h4", "bf16-h4"} <= set(names)
    assert {(c.name, c.budget) for c in defaults if c.budget} == {
        ("budget-auto-h4", "auto"), ("budget-0.6-h4", "0.6"), ("budget-0.35-h4", "0.35")}
    assert not any("fp16" in n or "compiled" in n or "graphs" in n for n in names)  # CUDA
    assert [c.name for c in select_configs("q25-h4,full-h1", 4)] == ["q25-h4", "full-h1"]
    with pytest.raises(ValueError, match="unknown configurations"):
        select_configs("full-h9", 4)
    path = tmp_path / "c.json"
    path.write_text(json.dumps([{"name": "mine", "frames": 2, "budget": "0.5"}]))
    assert select_configs(str(path), 4) == [SweepConfig("mine", frames=2, budget="0.5")]
    path.write_text(json.dumps([{"name": "bad", "speed": 3}]))
    with pytest.raises(ValueError, match="unknown keys"):
        select_configs(str(path), 4)
    for bad in ({"queries": 0.0}, {"compile": "reduce-overhead"}, {"precision": "fp8"}):
        with pytest.raises(ValueError):
            SweepConfig("x", **bad)
    assert SweepConfig("b", frames=2, budget="auto").describe().split() == [
        "b", "frames=2", "budget=auto"]


def test_list_configs_names_those_of_the_model_given_and_out_spares_shipped_results(
        tmp_path, capsys):
    from odg_ros.commands import build_parser, main
    checkpoint = write_tiny_checkpoint(tmp_path / "tiny.pt", image_size=(32, 88), num_frames=3)
    for argv, frames in ((["--checkpoint", str(checkpoint)], 3), ([], 4),   # shipped odg_cpu
                         (["--preset", "odg_t"], 8)):
        assert main(["bench", "--sweep", "--list-configs"] + argv) == 0
        lines = capsys.readouterr().out.splitlines()
        names = [line.split()[0] for line in lines[1:]]
        assert names[0] == f"full-h{frames}" and f"bf16-h{frames}" in names, lines
        assert all(not n.endswith(f"-h{k}") for n in names for k in (3, 4, 8) if k > frames)
    _, parser = build_parser("bench")
    out = parser.parse_args(["--sweep"]).out
    assert out == "bench_results" and not out.startswith("docs")


def test_cuda_sweeps_run_the_compiled_step_and_its_cuda_graphs(tmp_path):
    names = [c.name for c in select_configs(None, 4, device="cuda")]
    assert {"fp16-h4", "compiled-h4", "compiled-bf16-h4", "graphs-h4",
            "graphs-bf16-h4"} <= set(names)
    checkpoint = write_tiny_checkpoint(tmp_path / "tiny.pt", image_size=(32, 88), num_frames=3)
    with pytest.raises(ValueError, match="g: CUDA graphs need a CUDA device, not cpu"):
        prepare_model(checkpoint, "odg_cpu", "cpu", SweepConfig("g", compile="graphs"))


def test_plot_axes_never_collapse_onto_a_sliver():
    """Two configurations 0.001 FPS apart (the sweep of 2026-11-27: 2.5450-2.5460) get an FPS
    axis from 0, and scores 0.01 apart a score axis of at least SCORE_SPAN points."""
    low, high = axis_limits([2.5450, 2.5460], 1e-3, from_zero=True)
    assert low == 0.0 and 2.546 < high < 3.0
    low, high = axis_limits([18.32, 18.33], 2.0)
    assert high - low >= 2.0 and low < 18.32 and high > 18.33
    assert axis_limits([10.0, 30.0], 2.0) == pytest.approx((7.6, 32.4))
    assert axis_limits([None, float("nan")], 2.0, from_zero=True)[0] == 0.0
    assert axis_limits([0.0, 0.0], 2.0)[0] == 0.0 and axis_limits([-1.0, 0.0], 2.0)[0] < -1


# ------------------------------------------------------------------------ model variants
def test_query_budget_keeps_evenly_spaced_learned_queries():
    cfg = tiny_cfg()                      # 6 dynamic + 20 static queries
    model = ODG(cfg).eval()
    small, small_cfg = query_budget(model, cfg, 0.5)
    assert (small_cfg.num_dynamic, small_cfg.num_static) == (3, 10)
    q, s = model.queries.features.detach(), small.queries.features.detach()
    torch.testing.assert_close(s[:3], q[[0, 2, 5]])          # linspace(0, 5, 3).round()
    torch.testing.assert_close(s[3], q[6])
    torch.testing.assert_close(s[-1], q[-1])
    torch.testing.assert_close(small.queries.init_box.detach(),
                               model.queries.init_box.detach()[[0, 2, 5]])
    # every other weight is shared
    torch.testing.assert_close(small.decoder.layers[3].mixing.generator.weight,
                               model.decoder.layers[3].mixing.generator.weight)
    tiny, tiny_c = query_budget(model, cfg, 0.01)            # never zero of a kind
    assert (tiny_c.num_dynamic, tiny_c.num_static) == (1, 1)


def test_a_sample_is_fed_as_the_node_would_have_fed_its_frames(tmp_path):
    """Oldest frame first, stamps increasing by the time deltas, poses whose warps are the
    sample's; a frame the dataset repeats at a scene's start is fed once."""
    from odg_ros.geometry import ego_warp
    root = tmp_path / "world"
    data = write_tiny_split(root, 3)
    dataset = OccDataset(str(data), tiny_cfg())
    history, current = sample_camera_sets(dataset[2])            # 3 distinct frames
    assert len(history) == 2 and history[0][3] < history[1][3] < current[3]
    sample = dataset[2]
    for t, camera_set in enumerate([current] + history[::-1]):
        np.testing.assert_array_equal(camera_set[0], sample["images"][t].numpy())
        np.testing.assert_allclose(ego_warp(current[2], camera_set[2]),
                                   sample["ego_warp"][t].double().numpy(), atol=1e-6)
        assert current[3] - camera_set[3] == pytest.approx(float(sample["time_delta"][t]))
    history, current = sample_camera_sets(dataset[0])            # the scene's first keyframe
    assert history == [] and current[3] == 1000.0


# ------------------------------------------------------------------------ a whole sweep
@pytest.fixture(scope="module")
def tiny_split(tmp_path_factory):
    root = tmp_path_factory.mktemp("world")
    checkpoint = write_tiny_checkpoint(root / "tiny.pt", image_size=(32, 88), num_frames=3)
    return write_tiny_split(root, 3), checkpoint


def test_sweep_writes_json_and_png_with_every_measure(tiny_split, tmp_path):
    data, checkpoint = tiny_split
    configs = [SweepConfig("full-h3", frames=3), SweepConfig("q50-h2", frames=2, queries=0.5)]
    report = run_sweep(data, checkpoint, configs=configs, limit=2, repeats=1, warmup=0,
                       isolate=False, out=tmp_path, progress=False)
    saved = json.loads((tmp_path / "bench_cpu.json").read_text())
    png = tmp_path / "bench_cpu.png"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert set(saved) == {"meta", "configs", "pareto"}
    meta = saved["meta"]
    assert meta["random_weights"] is False and meta["checkpoint"] == str(checkpoint)
    assert meta["samples"] == 2 and meta["commit"] and meta["date"]
    assert len(meta["scene_load"]) == 2 and meta["quiet_samples"] and meta["busy_samples"]
    assert [c["config"]["name"] for c in saved["configs"]] == ["full-h3", "q50-h2"]
    for c in saved["configs"]:
        assert "error" not in c, c.get("traceback")
        assert set(c["latency_ms"]) >= {"step", "upload", "model", "download", "backbone",
                                        "decoder", "grid", "boxes", "visibility", "postprocess"}
        assert c["stages"] == "marks" and c["mode"] == "eager"
        assert len(c["decoder_layers_ms"]) == 6 and c["fps"] > 0 and c["peak_memory_mb"] > 0
        assert c["fps"] == pytest.approx(1e3 / c["latency_ms"]["step"], rel=1e-3)
        for key in ("mIoU", "RayIoU", "mIoU_dynamic", "IoU_geometry", "latency_ms", "box_mAP"):
            assert key in c["scores"]
        assert c["quiet"]["samples"] == 1 and c["busy"]["samples"] == 1
        assert len(c["per_sample"]) == 2
    full, budget = saved["configs"]
    assert full["frames"] == 3 and budget["frames"] == 2 and budget["queries"] == 13
    assert full["queries"] == 26
    assert set(saved["pareto"]) == {"mIoU", "RayIoU"} and saved["pareto"]["mIoU"]
    assert report["files"] == [str(tmp_path / "bench_cpu.json"), str(png)]


def test_sweep_scores_equal_offline_evaluation(tiny_split):
    """The sweep scores the node's step after each sample's history; it must match
    ``evaluate`` (the offline model over all frames) on the same samples: the same grids
    (float noise between the folded, channels-last step and the plain model may move a
    voxel), the same boxes (``odg eval`` scores every box, so the step keeps them all)."""
    data, checkpoint = tiny_split
    report = run_sweep(data, checkpoint, configs=[SweepConfig("full-h2", frames=2)], limit=3,
                       repeats=1, warmup=0, isolate=False, progress=False)
    model, cfg = load_model(checkpoint)
    expected = evaluate(model, cfg, str(data), limit=3, frames=2, progress=False)
    got = report["configs"][0]["scores"]
    for key in ("mIoU", "RayIoU", "IoU_geometry"):
        assert got[key] == pytest.approx(expected[key], abs=0.01), key
    assert got["box_mAP"] == pytest.approx(expected["boxes"]["mAP"], abs=0.01)


def test_sweep_in_a_fresh_process_reports_its_own_peak_memory(tiny_split):
    data, checkpoint = tiny_split
    report = run_sweep(data, checkpoint, configs=[SweepConfig("full-h1", frames=1)], limit=1,
                       repeats=1, warmup=0, isolate=True, progress=False)
    c = report["configs"][0]
    assert "error" not in c, c.get("traceback")
    assert report["meta"]["isolated_processes"] is True
    # the child's peak covers torch + the model, and is at least its after-load figure
    assert c["peak_memory_mb"] >= c["rss_after_load_mb"] > 50
    assert np.isfinite(c["fps"])


def test_another_model_in_the_sweep_is_flagged_and_kept_off_the_pareto_front(tiny_split,
                                                                             tmp_path):
    data, checkpoint = tiny_split
    preset = tmp_path / "other.yaml"
    values = {k: list(v) if isinstance(v, tuple) else v
              for k, v in tiny_cfg().replace(name="other", num_static=10).to_dict().items()}
    preset.write_text(json.dumps(values))            # JSON is YAML
    report = run_sweep(data, checkpoint, configs=[SweepConfig("mine", frames=1),
                                                  SweepConfig("other", frames=1,
                                                              model=str(preset))],
                       limit=1, repeats=1, warmup=0, isolate=False, progress=False)
    mine, other = report["configs"]
    assert mine["random_weights"] is False and other["random_weights"] is True
    assert other["model"] == "other" and other["queries"] == 16
    assert report["pareto"]["mIoU"] == ["mine"]


def test_random_weights_time_a_query_budget(tiny_split, tmp_path):
    """A preset's random weights have no trained budget heads; timing a budget needs none
    (the GPU timing of ODG-L's budgets), a checkpoint's untrained heads still stop it (the
    test above)."""
    from odg_ros.network.budget import budget_of
    data, checkpoint = tiny_split
    preset = tmp_path / "other.yaml"
    other = tiny_cfg().replace(name="other", num_static=20)
    preset.write_text(json.dumps({k: list(v) if isinstance(v, tuple) else v
                                  for k, v in other.to_dict().items()}))
    report = run_sweep(data, checkpoint, configs=[
        SweepConfig("other-b0.35", frames=1, model=str(preset), budget="0.35")],
        limit=1, repeats=1, warmup=0, isolate=False, progress=False)
    row = report["configs"][0]
    assert "error" not in row and row["random_weights"] is True
    expected = budget_of(other, 0.35).refined_fraction(other)
    assert expected < 0.5
    assert row["scores"]["refined_fraction"] == pytest.approx(expected, abs=1e-4)


def test_a_failing_configuration_is_reported_not_fatal(tiny_split):
    data, checkpoint = tiny_split
    report = run_sweep(data, checkpoint, configs=[SweepConfig("ok", frames=1),
                                                  SweepConfig("too-long", frames=9)],
                       limit=1, repeats=1, warmup=0, isolate=False, progress=False)
    assert "error" not in report["configs"][0]
    assert "at most 3" in report["configs"][1]["error"]
    with pytest.raises(RuntimeError, match="every sweep configuration failed"):
        run_sweep(data, checkpoint, configs=[SweepConfig("too-long", frames=9)], limit=1,
                  repeats=1, warmup=0, isolate=False, progress=False)


def test_query_budget_rows_say_how_many_queries_they_refined(tiny_split, tmp_path):
    """A budget row scores the budget's step exactly as ``evaluate`` at that budget does and
    reports the share of the queries it refined; a checkpoint without trained budget heads
    makes its budget rows fail, the rest of the sweep goes on."""
    from odg_ros.network.budget import budget_of
    from odg_ros.network.checkpoint import save_checkpoint
    data, untrained = tiny_split
    model, cfg = load_model(untrained)
    model.decoder.budget_heads.set_trained(True)
    checkpoint = tmp_path / "heads.pt"
    save_checkpoint(checkpoint, model)
    configs = [SweepConfig("full", frames=3), SweepConfig("half", frames=3, budget="0.5"),
               SweepConfig("auto", frames=3, budget="auto")]
    report = run_sweep(data, checkpoint, configs=configs, limit=3, repeats=1, warmup=0,
                       isolate=False, progress=False)
    rows = {r["config"]["name"]: r for r in report["configs"]}
    half = budget_of(cfg, 0.5)
    assert rows["full"]["scores"]["refined_fraction"] == 1.0
    assert rows["half"]["scores"]["refined_fraction"] == pytest.approx(
        half.refined_fraction(cfg), abs=1e-4)
    assert 0 < rows["auto"]["scores"]["refined_fraction"] <= 1.0
    expected = evaluate(model, cfg, str(data), limit=3, frames=3, progress=False, budget=half)
    for key in ("mIoU", "RayIoU", "IoU_geometry"):
        assert rows["half"]["scores"][key] == pytest.approx(expected[key], abs=0.01), key
    report = run_sweep(data, untrained, configs=configs[:2], limit=1, repeats=1, warmup=0,
                       isolate=False, progress=False)
    assert "error" not in report["configs"][0]
    assert "heads are not trained" in report["configs"][1]["error"]

