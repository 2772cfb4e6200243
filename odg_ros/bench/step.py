"""Latency of one online step: backbone on the newest frame, decoder over K cached frames,
post-processing; per decoder layer and per part of a layer; peak memory; the fast paths
against the plain path they replace.

Timing: medians over repeated steps after warm-up; on CUDA with events (no host sync inside
a step; one synchronise after it). Peak memory: on CUDA ``torch.cuda.max_memory_allocated``
over the timed steps; on CPU the process's peak resident set size (``ru_maxrss``), which
includes the interpreter, torch and the weights (the sweep runs every configuration in a
fresh process so each gets its own figure).
"""
from __future__ import annotations

import resource
import statistics
import sys
import time
from contextlib import contextmanager, nullcontext

import numpy as np
import torch
from tqdm import tqdm

from ..config import ModelConfig
from ..network import ODG
from ..network.feature_ring import FeatureRing
from ..network.postprocess import box_list, occupancy_grid
from ..network.precision import PRECISIONS, precision_context  # noqa: F401 (re-exported)
from ..rig import online_inputs, ring_ego2img

STAGES = ("backbone", "decoder", "postprocess", "total")
# the parts of a decoder layer, in execution order (attributes of decoder.DecoderLayer)
LAYER_PARTS = ("position", "box_position", "attention", "sampling", "mixing", "ffn", "points",
               "boxes")


class StageTimer:
    """Wall-clock per stage; on CUDA with events so no host sync sits inside a stage.
    Stages may nest (``total`` around the others) and be opened and closed by hooks."""

    def __init__(self, device):
        self.cuda = torch.device(device).type == "cuda"
        self.times: dict[str, list[float]] = {}
        self._pending = []
        self._open = {}

    def start(self, name: str) -> None:
        if self.cuda:
            event = torch.cuda.Event(enable_timing=True)
            event.record()
            self._open[name] = event
        else:
            self._open[name] = time.perf_counter()

    def stop(self, name: str) -> None:
        begin = self._open.pop(name)
        if self.cuda:
            end = torch.cuda.Event(enable_timing=True)
            end.record()
            self._pending.append((name, begin, end))
        else:
            self.times.setdefault(name, []).append((time.perf_counter() - begin) * 1e3)

    @contextmanager
    def stage(self, name: str):
        self.start(name)
        yield
        self.stop(name)

    def flush(self):
        if self._pending:
            torch.cuda.synchronize()
            for name, start, end in self._pending:
                self.times.setdefault(name, []).append(start.elapsed_time(end))
            self._pending.clear()

    def medians(self) -> dict[str, float]:
        self.flush()
        return {k: statistics.median(v) for k, v in self.times.items()}


class DecoderHooks:
    """Times every decoder layer (``layer1`` ..) and its parts (``layer1.sampling`` ..) with
    forward hooks into a ``StageTimer``; ``with DecoderHooks(model, timer):`` installs them.
    Under a query budget also the skip layer (``skip_layer``, ``skip_layer.attention`` ..)
    and the keep-scores (``keep_static``, ``keep_dynamic``; network/budget.py).
    The decoder time outside the layers (history layout without a ring, queries, Phi MLPs)
    is the decoder stage minus the layers (``decoder_outside_layers``)."""

    def __init__(self, model: ODG, timer: StageTimer):
        self.model, self.timer, self.handles = model, timer, []

    def _hook(self, module, name):
        def pre(*_):
            self.timer.start(name)

        def post(*_):
            self.timer.stop(name)
        self.handles += [module.register_forward_pre_hook(pre), module.register_forward_hook(post)]

    def __enter__(self):
        for index, layer in enumerate(self.model.decoder.layers):
            self._hook(layer, f"layer{index + 1}")
            for part in LAYER_PARTS:
                if getattr(layer, part, None) is not None:
                    self._hook(getattr(layer, part), f"layer{index + 1}.{part}")
        heads = self.model.decoder.budget_heads
        self._hook(heads.skip_layer, "skip_layer")
        for part in LAYER_PARTS:
            if getattr(heads.skip_layer, part, None) is not None:
                self._hook(getattr(heads.skip_layer, part), f"skip_layer.{part}")
        self._hook(heads.static_score, "keep_static")
        self._hook(heads.dynamic_score, "keep_dynamic")
        return self

    def __exit__(self, *exc):
        for handle in self.handles:
            handle.remove()
        self.handles.clear()


def layer_table(medians: dict[str, float], num_layers: int) -> list[dict]:
    """Per layer: total ms, ms per part, and ``other`` (norms, residuals, adds)."""
    rows = []
    for index in range(1, num_layers + 1):
        total = medians.get(f"layer{index}")
        if total is None:
            continue
        parts = {p: round(medians[f"layer{index}.{p}"], 3) for p in LAYER_PARTS
                 if f"layer{index}.{p}" in medians}
        rows.append({"layer": index, "total": round(total, 3), "parts": parts,
                     "other": round(total - sum(parts.values()), 3)})
    return rows


def peak_memory_mb(device) -> tuple[float, str]:
    """(peak MB, how it was measured) -- see the module docstring."""
    if torch.device(device).type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2 ** 20, "torch.cuda.max_memory_allocated"
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return (rss / 2 ** 20 if sys.platform == "darwin" else rss / 2 ** 10), "process ru_maxrss"


class TimedOnlineStep:
    """One online step as the node runs it: the backbone on the newest camera set, its
    features written into the ring (``ring=True``, ``ODG.decode_ring``) or kept in a list
    (``ODG.decode``), the decoder over the cached history, then the grid and the box list.

    ``prime(history)`` fills the cache with the older frames' features (untimed), newest
    first, as earlier steps would have; ``__call__`` runs and times the step, at the query
    ``budget`` set on it (network/budget.py; None: every query).
    """

    def __init__(self, model: ODG, cfg: ModelConfig, device, ring: bool = True,
                 precision: str = "fp32"):
        self.model, self.cfg, self.device = model, cfg, torch.device(device)
        self.ring = FeatureRing(cfg.num_frames, cfg.num_groups) if ring else None
        self.precision = precision
        self.history: list[list[torch.Tensor]] = []
        self.budget = None

    @torch.no_grad()
    def prime(self, history_features: list[list[torch.Tensor]]) -> None:
        """history_features: older frames, newest first (each L levels [1, N, C, h, w])."""
        self.history = list(history_features)
        if self.ring is not None:
            self.ring.clear()
            for feats in reversed(self.history):      # oldest first, like the node
                self.ring.push(feats)

    @torch.no_grad()
    def features(self, images: torch.Tensor) -> list[torch.Tensor]:
        with precision_context(self.precision, self.device):
            return self.model.extract_features(images)

    @torch.no_grad()
    def __call__(self, images, ego2img, ego_warp, time_delta, timer: StageTimer):
        """images [1, N, 3, H, W] of the newest set; geometry [1, T, ...] of the T frames
        (newest first) -> (output, grid labels [1, X, Y, Z], box list)."""
        with precision_context(self.precision, self.device), timer.stage("total"):
            with timer.stage("backbone"):
                current = self.model.extract_features(images)
                if self.ring is not None:
                    self.ring.push(current)
            with timer.stage("decoder"):
                if self.ring is not None:
                    output = self.model.decode_ring(self.ring, ego2img, ego_warp, time_delta,
                                                    budget=self.budget)
                else:
                    output = self.model.decode([current] + self.history, ego2img, ego_warp,
                                               time_delta, budget=self.budget)
            with timer.stage("postprocess"):
                grid, _ = occupancy_grid(output, self.cfg)
                boxes = box_list(output, self.cfg)
        return output, grid, boxes


def summarise(timer: StageTimer, num_layers: int) -> dict:
    medians = timer.medians()
    latency = {k: round(medians[k], 3) for k in STAGES if k in medians}
    layers = layer_table(medians, num_layers)
    if layers and "decoder" in medians:
        latency["decoder_outside_layers"] = round(
            medians["decoder"] - sum(r["total"] for r in layers), 3)
    return {"latency_ms": latency, "decoder_layers_ms": layers,
            "fps": round(1000.0 / medians["total"], 3) if "total" in medians else None}


@torch.no_grad()
def bench_online_step(cfg: ModelConfig, device="cpu", frames: int | None = None, iters: int = 5,
                      warmup: int = 1, progress: bool = True, model: ODG | None = None,
                      ring: bool = True, precision: str = "fp32",
                      layers: bool = True) -> dict:
    """Random inputs at the preset's resolution; random weights unless ``model`` is given."""
    frames = frames or cfg.num_frames
    if not 1 <= frames <= cfg.num_frames:
        raise ValueError(f"--frames must be in 1..{cfg.num_frames} for {cfg.name}")
    model = (model or ODG(cfg)).to(device).eval()
    images, ego2img, ego_warp, time_delta = online_inputs(cfg, frames, device)
    step = TimedOnlineStep(model, cfg, device, ring=ring, precision=precision)
    cached = step.features(images)  # stands in for the k-1 cached history frames
    cuda = torch.device(device).type == "cuda"
    timer = StageTimer(device)
    for i in tqdm(range(warmup + iters), desc=f"bench {cfg.name}", disable=not progress):
        if i == warmup:
            timer = StageTimer(device)
            if cuda:
                torch.cuda.reset_peak_memory_stats(device)
        step.prime([cached] * (frames - 1))
        with DecoderHooks(model, timer) if layers else nullcontext():
            step(images, ego2img, ego_warp, time_delta, timer)
        timer.flush()
    memory, method = peak_memory_mb(device)
    return {"preset": cfg.name, "device": str(device), "frames": frames, "iters": iters,
            "input": [cfg.num_cams, 3, *cfg.image_size], "threads": torch.get_num_threads(),
            "torch": torch.__version__, "precision": precision, "ring": ring,
            "fast_sampling": bool(model.fast_sampling),
            **summarise(timer, cfg.num_layers),
            "peak_memory_mb": round(memory, 1), "memory_method": method}


FAST_PATH_VARIANTS = {
    # name: (fast_sampling, ring, precision)
    "plain": (False, False, "fp32"),
    "camera_rows": (True, False, "fp32"),
    "camera_rows+ring": (True, True, "fp32"),
    "camera_rows+ring+bf16": (True, True, "bf16"),
}


@torch.no_grad()
def bench_fast_paths(cfg: ModelConfig, device="cpu", iters: int = 5, warmup: int = 1,
                     variants=tuple(FAST_PATH_VARIANTS), progress: bool = True) -> dict:
    """Each fast path against the plain path, interleaved step by step (a busy machine slows
    all variants alike), on one random-weights model and input; with the largest difference
    of the last layer's outputs from the plain path's."""
    torch.manual_seed(0)
    model = ODG(cfg).to(device).eval()
    images, ego2img, ego_warp, time_delta = online_inputs(cfg, cfg.num_frames, device)
    steps, timers, outputs = {}, {}, {}
    for name in variants:
        fast, ring, precision = FAST_PATH_VARIANTS[name]
        model.fast_sampling = fast
        steps[name] = TimedOnlineStep(model, cfg, device, ring=ring, precision=precision)
        timers[name] = StageTimer(device)
    history = None
    for i in tqdm(range(warmup + iters), desc=f"fast paths {cfg.name}", disable=not progress):
        for name in variants:
            step = steps[name]
            model.fast_sampling = FAST_PATH_VARIANTS[name][0]
            if history is None:
                history = [step.features(images)] * (cfg.num_frames - 1)
            if i == warmup:
                timers[name] = StageTimer(device)
            step.prime(history)
            outputs[name], _, _ = step(images, ego2img, ego_warp, time_delta, timers[name])
            timers[name].flush()
    model.fast_sampling = True
    reference = outputs[variants[0]].last
    result = {"preset": cfg.name, "device": str(device), "iters": iters,
              "threads": torch.get_num_threads(), "reference": variants[0], "variants": {}}
    for name in variants:
        last = outputs[name].last
        medians = timers[name].medians()
        result["variants"][name] = {
            "latency_ms": {k: round(medians[k], 3) for k in STAGES},
            "speedup_total": round(timers[variants[0]].medians()["total"] / medians["total"], 3),
            "max_abs_diff": {"means": float((last.means.float() - reference.means.float())
                                            .abs().max()),
                             "logits": float((last.logits.float() - reference.logits.float())
                                             .abs().max())}}
    return result


def node_inputs(cfg: ModelConfig, num_sets: int, seed: int = 0):
    """Camera sets as the node feeds its predictor: uint8 images, ego2img of a ring rig,
    poses of a car driving 10 m/s straight ahead, 0.5 s apart."""
    g = torch.Generator().manual_seed(seed)
    H, W = cfg.image_size
    ego2img = ring_ego2img(cfg.image_size, 1, cfg.num_cams)[0, 0].double().numpy()
    sets = []
    for k in range(num_sets):
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 3] = 5.0 * k
        images = torch.randint(0, 256, (cfg.num_cams, H, W, 3), generator=g,
                               dtype=torch.uint8).numpy()
        sets.append((images, ego2img, pose.numpy(), 10.0 + 0.5 * k))
    return sets


def data_camera_sets(infos_path, cfg: ModelConfig, num_sets: int):
    """The first ``num_sets`` keyframes of the first scene of an infos file as the node feeds
    its predictor (network-input uint8 images, ego2img, pose, stamp), 0.5 s apart."""
    from ..data.dataset import OccDataset
    dataset = OccDataset(infos_path, cfg)
    scene = dataset.infos[0]["scene_token"]
    infos = [info for info in dataset.infos if info["scene_token"] == scene][:num_sets]
    if len(infos) < num_sets:
        raise ValueError(f"{infos_path}: its first scene has {len(infos)} keyframes, "
                         f"{num_sets} asked for")
    sets = []
    for info in infos:
        pose = np.asarray(info["ego_pose"], dtype=np.float64)
        images = np.stack([dataset.load_image(info["cams"][name])
                           for name in dataset.camera_names])
        ego2img = dataset.frame_geometry(info["cams"], pose)[0]
        sets.append((images, ego2img, pose, info["timestamp"] / 1e6))
    return sets


def output_differences(output, reference, cfg: ModelConfig) -> dict:
    """The last decoder layer of ``output`` against ``reference``'s: max |logit difference|,
    and for the boxes valid in either, whether the valid sets agree and the largest centre
    (m), size (m) and score differences among the boxes valid in both (matched by query)."""
    from ..network.postprocess import decode_box_code
    a, b = output.last, reference.last
    result = {"logits": float((a.logits.float() - b.logits.float()).abs().max())}
    if a.boxes is None:
        return result
    score_a = a.box_logits.float().sigmoid().amax(-1)
    score_b = b.box_logits.float().sigmoid().amax(-1)
    valid_a = score_a > cfg.box_score_threshold
    valid_b = score_b > cfg.box_score_threshold
    both = valid_a & valid_b
    box_a, box_b = decode_box_code(a.boxes.float()), decode_box_code(b.boxes.float())
    gap = (box_a - box_b).abs()

    def largest(t):
        return float(t[both].max()) if both.any() else 0.0
    result.update(boxes_valid=int(valid_b.sum()), boxes_valid_mismatch=int((valid_a ^ valid_b)
                                                                         .sum()),
                  box_centre_m=largest(gap[..., :3].amax(-1)),
                  box_size_m=largest(gap[..., 3:6].amax(-1)),
                  box_score=largest((score_a - score_b).abs()))
    return result


def bench_node_step(cfg: ModelConfig, device="cpu", modes=("eager", "compiled"),
                    iters: int = 5, warmup: int = 1, precisions=("fp32",),
                    model: ODG | None = None, progress: bool = True, sets=None,
                    compiled_step=None) -> dict:
    """``OnlinePredictor.step`` (what the node runs per camera set: upload, the device step,
    download) for each execution mode and precision, interleaved set by set over one stream of
    sets (``sets``: the node's inputs, default ``node_inputs``, random); the history fills as
    in the node. Everything is compared with the first variant's: the grid (all voxels, and
    the voxels occupied in either), and the last layer's logits and boxes
    (``output_differences``). A variant is named by its mode, plus its precision where
    several are asked for. ``compiled_step``: a .pt2 of ``odg export --aoti`` that the
    compiled and graphs variants run instead of compiling."""
    from ..online.predictor import OnlinePredictor
    model = (model or ODG(cfg)).to(device).eval()
    variants = {(mode if len(precisions) == 1 else f"{mode}-{precision}"): (mode, precision)
                for precision in precisions for mode in modes}
    predictors = {name: OnlinePredictor(model, cfg, device, max_gap=1.0, precision=precision,
                                        compile=mode,
                                        compiled_step=None if mode == "eager" else compiled_step)
                  for name, (mode, precision) in variants.items()}
    sets = sets if sets is not None else node_inputs(cfg, warmup + iters)
    times = {name: {"step": [], "upload": [], "model": [], "download": []} for name in variants}
    agreement = {name: [] for name in variants}
    occupied_agreement = {name: [] for name in variants}
    differences = {name: [] for name in variants}
    for i, camera_set in enumerate(tqdm(sets, desc=f"node step {cfg.name}",
                                        disable=not progress)):
        results, outputs = {}, {}
        for name in variants:
            start = time.perf_counter()
            results[name] = predictors[name].step(*camera_set)
            if i >= warmup:
                times[name]["step"].append((time.perf_counter() - start) * 1e3)
                for stage, seconds in results[name].timings.items():
                    times[name][stage].append(seconds * 1e3)
            if len(precisions) > 1:          # untimed: the decoder again, for its raw output
                with torch.inference_mode():
                    outputs[name] = predictors[name]._raw_output()
        first_name = next(iter(variants))
        first = results[first_name].grid
        for name in variants:
            grid = results[name].grid
            agreement[name].append(float((grid == first).mean()))
            occupied = (grid != cfg.num_classes) | (first != cfg.num_classes)
            occupied_agreement[name].append(float((grid[occupied] == first[occupied]).mean())
                                            if occupied.any() else 1.0)
            if outputs:
                differences[name].append(output_differences(outputs[name],
                                                             outputs[first_name], cfg))
    step_times = {name: statistics.median(t["step"]) for name, t in times.items()}
    reference = step_times[first_name]
    result = {"preset": cfg.name, "device": str(device), "iters": iters,
              "threads": torch.get_num_threads(), "torch": torch.__version__,
              "precisions": list(precisions), "input": [cfg.num_cams, 3, *cfg.image_size],
              "frames": cfg.num_frames, "sets": len(sets), "reference": first_name,
              "modes": {}}
    for name, (mode, precision) in variants.items():
        entry = {"mode": mode, "precision": precision,
                 "latency_ms": {k: round(statistics.median(v), 3) for k, v in
                                times[name].items()},
                 "fps": round(1e3 / step_times[name], 2),
                 "speedup": round(reference / step_times[name], 3),
                 "startup_s": round(predictors[name].startup_seconds, 2),
                 "grid_agreement_min": min(agreement[name]),
                 "occupied_agreement_min": min(occupied_agreement[name])}
        if differences[name]:
            entry["max_difference"] = {key: max(d[key] for d in differences[name])
                                       for key in differences[name][0]}
        result["modes"][name] = entry
    return result
