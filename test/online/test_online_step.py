"""The static-shape online step (online/step.py): the same outputs as the dynamic ring path
at every fill level, one trace for every step, no host read inside it, compiled == eager."""
import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from odg_ros.geometry import ego_warp
from odg_ros.network.feature_ring import FeatureRing
from odg_ros.network.postprocess import box_list, occupancy_grid
from odg_ros.online.predictor import OnlinePredictor, resolve_mode
from odg_ros.preprocess import normalize
from testing.helpers import assert_layers_close, assert_published_like
from testing.online import (HostSyncCounter, eager_reference, make_model, make_sets,
                            raw_output, stepped_predictor)

from testing import reference_postprocess


def dynamic_ring_outputs(model, cfg, sets, capacity):
    """The per-step ring path the static step replaces: a ring of the filled slots only
    and geometry of the T frames held (``ODG.decode_ring``)."""
    ring, held, outputs = FeatureRing(capacity, cfg.num_groups), [], []
    with torch.inference_mode():
        for images, ego2img, pose, stamp in sets:
            x = normalize(torch.from_numpy(images))
            ring.push(model.extract_features(x[None]))
            held = [(ego2img, pose, stamp)] + held[:capacity - 1]
            current = held[0]
            e2i = torch.tensor(np.stack([h[0] for h in held]), dtype=torch.float32)[None]
            warps = torch.tensor(np.stack([ego_warp(current[1], h[1]) for h in held]),
                                 dtype=torch.float32)[None]
            deltas = torch.tensor([current[2] - h[2] for h in held], dtype=torch.float32)[None]
            outputs.append(model.decode_ring(ring, e2i, warps, deltas))
    return outputs


@pytest.mark.parametrize("capacity", [3, 2])
def test_static_step_equals_the_dynamic_ring_at_every_fill_level(capacity):
    """Steps 1..k fill the ring, later ones wrap around; k < num_frames repeats the oldest
    for the missing time steps. Raw decoder outputs, grid and boxes all agree."""
    model, cfg = make_model()
    sets = make_sets(cfg, 5)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, num_frames=capacity)
    reference = dynamic_ring_outputs(model, cfg, sets, capacity)
    for i, (s, expected) in enumerate(zip(sets, reference)):
        online = predictor.step(*s)
        assert online.num_frames == min(i + 1, capacity)
        assert_layers_close(raw_output(predictor).layers, expected.layers, 1e-5)
        assert_published_like(online, expected, cfg, atol=1e-4)


def test_the_step_reads_nothing_back_and_copies_nothing_up():
    predictor, model, cfg, sets = stepped_predictor(2)
    with torch.inference_mode(), HostSyncCounter() as counter:
        predictor.online_step(predictor._images, predictor._packed)
    assert counter.ops > 1000 and counter.syncs == []
    # the counter sees what it looks for: the loop post-processing reads sizes back
    output = dynamic_ring_outputs(model, cfg, sets[:1], 3)[0]
    with torch.inference_mode(), HostSyncCounter() as counter:
        reference_postprocess.occupancy_grid(output, cfg)
        reference_postprocess.box_list(output, cfg)
    assert {"_unique2", "boolean index", "lift_fresh"} <= set(counter.syncs)
    # (a Python read of a CPU tensor's value does not dispatch: fullgraph=True tracing, in
    # test_one_graph_over_the_first_twelve_steps, fails on any such read in the step)


def test_one_graph_over_the_first_twelve_steps():
    """fullgraph=True, dynamic=False, a backend that counts the graphs it is given: history
    fill levels, wrap-around, a replaced provisional frame and a reset all reuse one graph,
    and every step of the traced graph equals eager. (With ``aot_eager`` in place of
    ``graph_module.forward``, i.e. functionalised as Inductor gets it, ring write included,
    it passes too, in ~2 minutes.)"""
    model, cfg = make_model()
    graphs = []

    def counting_backend(graph_module, example_inputs):
        graphs.append(graph_module)
        return graph_module.forward

    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, min_interval=0.9)
    predictor._function = torch.compile(predictor.online_step, backend=counting_backend,
                                        fullgraph=True, dynamic=False)
    predictor._warm_up()            # compiled at start-up, as the constructor does
    sets = make_sets(cfg, 11)
    eager = eager_reference(model, cfg, max_gap=1.0, min_interval=0.9)
    for s in sets + [sets[0]]:                       # the last one goes back in time: reset
        a, b = predictor.step(*s), eager.step(*s)
        np.testing.assert_array_equal(a.grid, b.grid)
        np.testing.assert_array_equal(a.confidence, b.confidence)
        assert a.boxes == b.boxes
    assert len(graphs) == 1
    assert a.history_reset == "time_backwards"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA GPU")
@pytest.mark.parametrize("mode", ["compiled", "graphs"])
def test_cuda_modes_equal_eager_through_fill_wrap_and_reset(mode):
    """On a GPU: the compiled step and its CUDA-graph replay give eager's outputs over the
    ring's fill levels, its wrap-around and a reset, and a result handed out stays as it was
    while later replays reuse the graph's buffers."""
    model, cfg = make_model()
    model = model.cuda()
    predictor = OnlinePredictor(model, cfg, "cuda", max_gap=1.0, min_interval=0.9,
                                compile=mode)
    eager = OnlinePredictor(model, cfg, "cuda", max_gap=1.0, min_interval=0.9)
    assert predictor.mode == mode and predictor.startup_seconds > 0
    sets = make_sets(cfg, 11)
    first = None
    for s in sets + [sets[0]]:                       # the last one goes back in time: reset
        a, b = predictor.step(*s), eager.step(*s)
        first = first or (a, a.grid.copy(), a.confidence.copy())
        assert (a.grid == b.grid).mean() >= 0.999    # float noise of other kernels only
        assert np.abs(a.confidence.astype(int) - b.confidence).max() <= 2
        assert len(a.boxes) == len(b.boxes) and a.num_frames == b.num_frames
    assert a.history_reset == "time_backwards"
    np.testing.assert_array_equal(first[0].grid, first[1])
    np.testing.assert_array_equal(first[0].confidence, first[2])


def test_execution_modes():
    assert resolve_mode("auto", "cuda") == "graphs"
    assert resolve_mode("auto", "cpu") in ("eager", "compiled")
    with pytest.raises(ValueError, match="CUDA"):
        resolve_mode("graphs", "cpu")
    with pytest.raises(ValueError, match="expected"):
        resolve_mode("fast", "cpu")


def random_output(seed, classes, batch=2, queries=40, points=8, dynamic=10):
    """Points crowded into a few voxels (shared voxels average), some NaN / far / outside,
    scores around the threshold; box codes with a NaN one and score ties."""
    from odg_ros.network.outputs import LayerOutput, ODGOutput
    g = torch.Generator().manual_seed(seed)
    centres = torch.rand(batch, queries, 1, 3, generator=g) * torch.tensor([6.0, 6.0, 2.0])
    means = centres + torch.randn(batch, queries, points, 3, generator=g) * 0.6
    means[0, 0, 0] = float("nan")
    means[1, 1, :2, 0] = 45.0                                 # outside the grid
    means[0, 2] = torch.tensor([39.9, -39.9, 5.3])            # inside, at the far faces
    logits = torch.randn(batch, queries, points, classes, generator=g) * 2.0
    boxes = torch.randn(batch, dynamic, 10, generator=g)
    boxes[0, 3, 4] = float("nan")
    box_logits = torch.randn(batch, dynamic, 10, generator=g)
    box_logits[1, 4:6] = 3.0                                  # equal scores
    layer = LayerOutput(means, logits, None, None, None, boxes, box_logits)
    return ODGOutput(init_means=means[:, :, :1], layers=[layer], num_dynamic=dynamic)


@pytest.mark.parametrize("classes", [17, 15])
def test_static_postprocess_equals_the_loop_postprocess(classes):
    """15 classes: Occ3D-Waymo's label set, free = 15."""
    model, cfg = make_model()
    cfg = cfg.replace(score_threshold=0.5, box_score_threshold=0.3, num_classes=classes,
                      dataset="waymo" if classes == 15 else "nuscenes")
    for seed in range(3):
        output = random_output(seed, classes)
        labels, confidence = occupancy_grid(output, cfg)
        ref_labels, ref_confidence = reference_postprocess.occupancy_grid(output, cfg,
                                                                          free_label=classes)
        assert 20 < (ref_labels != classes).sum() < (ref_labels != classes).numel()
        torch.testing.assert_close(labels, ref_labels, atol=0, rtol=0)
        assert (confidence.int() - ref_confidence.int()).abs().max() <= 1
        boxes, ref_boxes = box_list(output, cfg), reference_postprocess.box_list(output, cfg)
        assert sum(map(len, ref_boxes)) > 4
        for a, b in zip(boxes, ref_boxes):
            assert [x["score"] for x in a] == [x["score"] for x in b]
            assert sorted(map(str, a)) == sorted(map(str, b))    # ties in any order


def test_bench_times_the_predictor_step_and_its_stages_from_the_marks():
    from odg_ros.bench.step_timing import bench_node_step
    model, cfg = make_model()
    # fp32: eager agrees with the reference exactly (precision auto may pick bf16 here)
    result = bench_node_step(cfg, "cpu", ("eager",), iters=2, warmup=1, precisions=("fp32",),
                             model=model, progress=False)
    assert result["settings"]["visibility"] is True and result["steps"] == 5
    eager = result["modes"]["eager"]
    lat = eager["latency_ms"]
    assert {"step", "upload", "model", "download"} <= set(lat)
    assert lat["step"] >= lat["model"] > 0
    # the step's own stages, padding (the tiny model pads) and visibility included
    assert eager["stages"] == "marks"
    assert {"backbone", "decoder", "grid", "padding", "boxes", "visibility"} <= set(lat)
    assert len(eager["decoder_layers_ms"]) == cfg.num_layers
    for row in eager["decoder_layers_ms"]:
        assert {"attention", "sampling", "mixing"} <= set(row["parts"])
        assert row["total"] >= sum(row["parts"].values()) - 1e-6
    assert sum(r["total"] for r in eager["decoder_layers_ms"]) <= lat["decoder"]
    assert eager["grid_agreement_min"] == 1.0 and eager["startup_s"] > 0
    assert result["peak_memory_mb"] > 50 and result["memory_method"] == "process ru_maxrss"


def test_without_a_recorder_the_marks_record_nothing():
    """The node's step pays for its marks only while a recorder or a profiler is on."""
    from odg_ros.online import marks
    model, cfg = make_model()
    predictor = OnlinePredictor(model, cfg, "cpu")
    recorder = marks.MarkRecorder("cpu")
    predictor.step(*make_sets(cfg, 1)[0])
    assert recorder.times == {} and marks._recorder is None
    assert marks.mark("decoder") is marks._NOTHING                 # no range, no timer
    with recorder:
        predictor.step(*make_sets(cfg, 2)[1])
    assert set(recorder.times) == {"backbone", "decoder", "grid", "padding", "boxes",
                                   "visibility"}
    with torch.profiler.profile() as profile:
        predictor.step(*make_sets(cfg, 3)[2])
    assert {e.name for e in profile.events() if e.name.startswith(marks.PREFIX)} == {
        "odg.backbone", "odg.decoder", "odg.grid", "odg.padding", "odg.boxes",
        "odg.visibility"}
    # traced by torch.compile (fullgraph) while both record: one graph, and no marks in it
    graphs = []
    compiled = OnlinePredictor(model, cfg, "cpu")
    compiled._function = torch.compile(
        compiled.online_step, backend=lambda gm, _: graphs.append(gm) or gm.forward,
        fullgraph=True, dynamic=False)
    recorder = marks.MarkRecorder("cpu")
    with recorder, torch.profiler.profile() as profile:
        compiled._warm_up()
        compiled.step(*make_sets(cfg, 1)[0])
    assert len(graphs) == 1 and recorder.times == {}
    assert not [e.name for e in profile.events() if e.name.startswith(marks.PREFIX)]


def test_bench_compares_each_variant_with_eager_fp32(tmp_path, capsys):
    """``odg bench --compile eager --precision fp32,bf16 --data INFOS``: both variants step
    over the split's keyframes; bf16's own grid, confidence and boxes are compared with
    fp32's."""
    import json
    from testing.helpers import write_tiny_checkpoint, write_tiny_split
    from odg_ros.commands import main
    checkpoint = write_tiny_checkpoint(tmp_path / "tiny.pt", score_threshold=0.0,
                                       box_score_threshold=0.0)
    infos = write_tiny_split(tmp_path / "world", num_keyframes=3)
    assert main(["bench", "--compile", "eager", "--precision", "fp32,bf16", "--checkpoint",
                 str(checkpoint), "--data", str(infos), "--iters", "2", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["distinct_sets"] == 3 and result["reference"] == "eager-fp32"
    fp32, bf16 = result["modes"]["eager-fp32"], result["modes"]["eager-bf16"]
    assert fp32["max_difference"]["confidence"] == 0 and fp32["occupied_agreement_min"] == 1
    assert fp32["max_difference"]["boxes_unmatched"] == 0
    assert 0 < bf16["max_difference"]["confidence"] < 128                 # bf16 rounding
    assert bf16["max_difference"]["boxes_valid"] > 0
    assert bf16["max_difference"]["box_centre_m"] < 1.0
    assert 0.5 < bf16["occupied_agreement_min"] <= 1


class WeightCastCounter(TorchDispatchMode):
    """Counts dtype casts whose source is one of ``weights`` (by storage)."""

    def __init__(self, weights):
        super().__init__()
        self.storages = {w.untyped_storage().data_ptr() for w in weights}
        self.casts = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func.overloadpacket.__name__ in ("to", "_to_copy") and \
                args[0].untyped_storage().data_ptr() in self.storages:
            self.casts += 1
        return func(*args, **(kwargs or {}))


def test_bf16_step_stores_its_matrix_weights_in_bf16_and_casts_none():
    """Autocast over float32 weights casts every Linear / convolution weight at every step;
    the bf16 step keeps them in bf16 (a copy: the shared model stays float32) and casts none,
    with the same outputs as autocast over float32 weights to the bit (measured on odg_cpu)."""
    model, cfg = make_model()
    sets = make_sets(cfg, 2)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, precision="bf16")
    step = predictor.online_step
    running = [m for part in (step.backbone, step.neck, step.model.decoder)
               for m in part.modules()]
    matrices = [m for m in running if isinstance(m, (torch.nn.Linear, torch.nn.Conv2d))]
    assert len(matrices) > 50 and all(m.weight.dtype == torch.bfloat16 for m in matrices)
    assert all(p.dtype == torch.float32 for p in model.parameters())       # not mutated
    norms = [m for m in running if isinstance(m, torch.nn.LayerNorm)]
    assert norms and all(m.weight.dtype == torch.float32 for m in norms)
    predictor.step(*sets[0])
    weights = [p for p in step.parameters()] + list(model.parameters())
    with torch.inference_mode(), WeightCastCounter(weights) as counter:
        predictor.online_step(predictor._images, predictor._packed)
    assert counter.casts == 0
    # the counter sees weight casts: autocast over the float32 model casts each weight
    with torch.inference_mode(), WeightCastCounter(model.parameters()) as counter, \
            torch.autocast("cpu", dtype=torch.bfloat16):
        model.extract_features(torch.zeros(1, cfg.num_cams, 3, *cfg.image_size))
    assert counter.casts > 20


def test_bf16_encoder_step_runs_the_encoder_in_bf16_and_the_decoder_in_fp32():
    """bf16-encoder: ResNet and FPN weights in bf16, the decoder's float32 and shared with
    the model, no autocast around it; its published grid and boxes are the fp32 decoder's
    on the same (bf16-rounded) features."""
    model, cfg = make_model()
    sets = make_sets(cfg, 2)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, precision="bf16-encoder")
    step = predictor.online_step
    encoder = [m for part in (step.backbone, step.neck) for m in part.modules()
               if isinstance(m, torch.nn.Conv2d)]
    assert len(encoder) > 20 and all(m.weight.dtype == torch.bfloat16 for m in encoder)
    assert step.model.decoder is model.decoder
    assert all(p.dtype == torch.float32 for p in model.parameters())       # not mutated
    for s in sets:
        online = predictor.step(*s)
    ego2img, warps, deltas, frame_index, _ = step.layout.unpack(predictor._packed)
    with torch.inference_mode():
        fp32 = model.decode_stored(step.ring.all_levels(), ego2img, warps, deltas,
                                   frame_index, False)
    assert_published_like(online, fp32, cfg, atol=1e-5)
    features = step.ring.all_levels()[0]
    assert features.dtype == torch.float32 and features.abs().sum() > 0
    assert torch.equal(features, features.bfloat16().float())          # bf16 values


def test_eager_cpu_step_runs_the_encoder_on_torchs_threads_and_the_rest_on_one():
    """The node's eager CPU step: the encoder (and the ring write) on the threads torch has,
    the decoder and everything after it on one; torch's count is back after the step, and a
    predictor told to use every thread throughout (what a compiled step does) keeps them."""
    model, cfg = make_model()
    seen = []
    def record(stage):
        return lambda module, inputs, output: seen.append((stage, torch.get_num_threads()))
    threads_before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        for parallel_throughout in (False, True):
            predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0)
            assert predictor.online_step.parallel_encoder_only
            predictor.online_step.parallel_encoder_only = not parallel_throughout
            step = predictor.online_step
            hooks = [step.backbone.register_forward_hook(record("encoder")),
                     step.model.decoder.register_forward_hook(record("decoder"))]
            seen.clear()
            predictor.step(*make_sets(cfg, 1)[0])
            for hook in hooks:
                hook.remove()
            expected = [("encoder", 2), ("decoder", 2 if parallel_throughout else 1)]
            assert seen == expected and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads_before)
