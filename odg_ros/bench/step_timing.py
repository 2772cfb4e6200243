"""``odg bench``: the node's own step, timed per camera set.

What is timed is ``OnlinePredictor.step``, the call the node makes per camera set: the host
packs the geometry and uploads the images, ``OnlineStep`` runs (backbone on the newest set,
decoder over the feature ring, grid with padding, ranked boxes, visibility), the results come
back. It runs at the node's settings (config/odg_node.schema.yaml: precision, compile,
query_budget, visibility, history) unless a variant says otherwise. Several variants
(execution modes x precisions) take turns set by set over one stream of camera sets, so a
busy machine slows them alike.

Per stage and per decoder layer: the step's own marks (online/marks.py), recorded on steps
of their own (as many as the timed ones, taking turns with them) of eager variants; the step
times (and FPS) come from the timed steps, with nothing recording. A compiled or
graph-replayed step has no marks inside: it is timed whole. Medians throughout. On CUDA the
marks are CUDA events, read after the step.

Each variant's grid (labels and confidence) and boxes are compared with an eager fp32 step
of the same model on the same sets (one of the variants, or an untimed extra).

Peak memory: on CUDA ``torch.cuda.max_memory_allocated``; on CPU the process's peak resident
set size (``ru_maxrss``: interpreter, torch, weights and every variant together).
"""
from __future__ import annotations

import resource
import statistics
import sys
import time

import numpy as np
import torch
from tqdm import tqdm

from ..model_config import ModelConfig
from ..network import ODG
from ..network.precision import resolve_precision
from ..online.marks import LAYER_PARTS, STEP_STAGES, DecoderMarks, MarkRecorder
from ..online.execution import resolve_mode
from ..online.predictor import OnlinePredictor
from ..nuscenes_cameras import ring_ego2img

# the node's parameters that shape its step and history (their defaults: the schema's)
NODE_SETTINGS = ("precision", "compile", "query_budget", "visibility", "history_interval",
                 "history_max_gap")
HOST_STAGES = ("step", "upload", "model", "download")
POSTPROCESS = ("grid", "padding", "boxes", "visibility")
BOX_MATCH_M = 2.0              # boxes of two runs farther apart than this are not one box


def node_settings(**overrides) -> dict:
    """The node's defaults for NODE_SETTINGS (config/odg_node.schema.yaml), with the given
    ones (None: the default) put in."""
    from ..online.parameters import load_schema
    schema = load_schema()
    settings = {name: schema[name].default for name in NODE_SETTINGS}
    settings.update({k: v for k, v in overrides.items() if v is not None})
    unknown = set(settings) - set(NODE_SETTINGS)
    if unknown:
        raise ValueError(f"unknown node settings {sorted(unknown)}")
    return settings


def node_predictor(model, cfg: ModelConfig, device, settings: dict, mode: str | None = None,
                   precision: str | None = None, frames: int | None = None,
                   compiled_step=None) -> OnlinePredictor:
    """An ``OnlinePredictor`` built as the node builds it (ros/node.py) from ``settings``;
    ``mode`` / ``precision`` replace the settings' compile / precision."""
    return OnlinePredictor(model, cfg, device, max_gap=float(settings["history_max_gap"]),
                           num_frames=frames, min_interval=float(settings["history_interval"]),
                           precision=precision or settings["precision"],
                           compile=mode or settings["compile"], compiled_step=compiled_step,
                           visibility=bool(settings["visibility"]),
                           query_budget=settings["query_budget"])


def peak_memory_mb(device) -> tuple[float, str]:
    """(peak MB, how it was measured) -- see the module docstring."""
    if torch.device(device).type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2 ** 20, "torch.cuda.max_memory_allocated"
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return (rss / 2 ** 20 if sys.platform == "darwin" else rss / 2 ** 10), "process ru_maxrss"


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


def stage_summary(medians: dict[str, float], num_layers: int) -> dict:
    """Marks' medians -> {"latency_ms": the step's stages, ``postprocess`` (grid, padding,
    boxes, visibility together) and ``decoder_outside_layers`` (queries, Phi MLPs, the
    budget's keep-scores), "decoder_layers_ms": ``layer_table``, "budget_ms": the skip layer
    and keep-score marks}; empty where nothing was marked (a compiled step)."""
    latency = {k: round(medians[k], 3) for k in STEP_STAGES if k in medians}
    if not latency:
        return {"latency_ms": {}, "decoder_layers_ms": [], "budget_ms": {}}
    latency["postprocess"] = round(sum(medians.get(k, 0.0) for k in POSTPROCESS), 3)
    layers = layer_table(medians, num_layers)
    if layers and "decoder" in medians:
        latency["decoder_outside_layers"] = round(
            medians["decoder"] - sum(r["total"] for r in layers), 3)
    budget = {name: round(ms, 3) for name, ms in medians.items()
              if name.startswith(("skip_layer", "keep_"))}
    return {"latency_ms": latency, "decoder_layers_ms": layers, "budget_ms": budget}


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


def data_camera_sets(infos_path, cfg: ModelConfig, num_sets: int | None = None):
    """The keyframes of the first scene of an infos file (the first ``num_sets``) as the
    node feeds its predictor (network-input uint8 images, ego2img, pose, stamp, each image's
    bounds in network-input pixels), 0.5 s apart."""
    from ..data.dataset import OccDataset
    from ..preprocess import image_bounds
    dataset = OccDataset(infos_path, cfg)
    if not dataset.infos:
        raise ValueError(f"{infos_path}: no keyframes")
    scene = dataset.infos[0]["scene_token"]
    infos = [info for info in dataset.infos if info["scene_token"] == scene][:num_sets]
    sets = []
    for info in infos:
        pose = np.asarray(info["ego_pose"], dtype=np.float64)
        images = np.stack([dataset.load_image(info["cams"][name])
                           for name in dataset.camera_names])
        ego2img = dataset.frame_geometry(info["cams"], pose)[0]
        bounds = image_bounds([info["cams"][name]["image_hw"] for name in dataset.camera_names],
                              dataset.image_size)
        sets.append((images, ego2img, pose, info["timestamp"] / 1e6, bounds))
    return sets


def prediction_differences(prediction, reference, cfg: ModelConfig) -> dict:
    """One set's ``Prediction`` against ``reference``'s (both what the node publishes): the
    share of voxels with the same label, of the voxels occupied in either, the largest
    confidence difference (0..255), and the boxes: matched one to one by centre distance
    (same class, at most BOX_MATCH_M apart; scipy's Hungarian solver), how many are left
    unmatched and the largest centre (m), size (m) and score differences of the matched."""
    from scipy.optimize import linear_sum_assignment
    grid, ref = prediction.grid, reference.grid
    occupied = (grid != cfg.num_classes) | (ref != cfg.num_classes)
    result = {"grid_agreement": float((grid == ref).mean()),
              "occupied_agreement": float((grid[occupied] == ref[occupied]).mean())
              if occupied.any() else 1.0,
              "confidence": int(np.abs(prediction.confidence.astype(np.int16)
                                       - reference.confidence).max()),
              "boxes_valid": len(reference.boxes)}
    a, b = prediction.boxes, reference.boxes
    pairs = []
    if a and b:
        centres = [np.array([box["center"] for box in boxes]) for boxes in (a, b)]
        cost = np.linalg.norm(centres[0][:, None] - centres[1][None], axis=-1)
        cost[np.not_equal.outer([x["label"] for x in a], [x["label"] for x in b])] = 1e6
        pairs = [(i, j) for i, j in zip(*linear_sum_assignment(cost))
                 if cost[i, j] <= BOX_MATCH_M]

    def largest(values):
        return float(max(values, default=0.0))
    result.update(
        boxes_unmatched=len(a) + len(b) - 2 * len(pairs),
        box_centre_m=largest(np.linalg.norm(np.subtract(a[i]["center"], b[j]["center"]))
                             for i, j in pairs),
        box_size_m=largest(np.abs(np.subtract(a[i]["size"], b[j]["size"])).max()
                           for i, j in pairs),
        box_score=largest(abs(a[i]["score"] - b[j]["score"]) for i, j in pairs))
    return result


class Variant:
    """One execution mode and precision of the node's step: its predictor, its step times
    (``times``: ms per host stage, steps without marks) and marks (``recorder``)."""

    def __init__(self, name, mode, precision, predictor):
        self.name, self.mode, self.precision, self.predictor = name, mode, precision, predictor
        self.times = {stage: [] for stage in HOST_STAGES}
        self.recorder = MarkRecorder(predictor.device)
        self.differences: list[dict] = []

    def step(self, camera_set, marks: bool = False, timed: bool = True):
        """One ``predictor.step``, timed whole; with ``marks``, recorded by the step's marks
        and the decoder layers' instead (not timed: the recording costs a little), or not at
        all in a mode without marks."""
        if marks and self.mode == "eager":
            decoder = self.predictor.online_step.model.decoder
            with self.recorder, DecoderMarks(decoder, self.recorder):
                prediction = self.predictor.step(*camera_set)
            self.recorder.flush()
            return prediction
        start = time.perf_counter()
        prediction = self.predictor.step(*camera_set)
        if timed and not marks:
            self.times["step"].append((time.perf_counter() - start) * 1e3)
            for stage, seconds in prediction.timings.items():
                self.times[stage].append(seconds * 1e3)
        return prediction

    def result(self, cfg: ModelConfig, reference_ms: float | None = None) -> dict:
        """Medians, FPS, the stages, and with ``reference_ms`` (another variant's step) the
        speed-up against it."""
        latency = {k: round(statistics.median(v), 3) for k, v in self.times.items() if v}
        stages = stage_summary(self.recorder.medians(), cfg.num_layers)
        entry = {"mode": self.mode, "precision": self.precision,
                 "latency_ms": {**latency, **stages["latency_ms"]},
                 "fps": round(1e3 / latency["step"], 3),
                 "startup_s": round(self.predictor.startup_seconds, 2),
                 "stages": "marks" if stages["latency_ms"] else
                 f"whole step only: no marks inside a {self.mode} step",
                 "decoder_layers_ms": stages["decoder_layers_ms"],
                 "budget_ms": stages["budget_ms"]}
        if reference_ms is not None:
            entry["speedup"] = round(reference_ms / latency["step"], 3)
        if self.differences:
            entry["grid_agreement_min"] = min(d["grid_agreement"] for d in self.differences)
            entry["occupied_agreement_min"] = min(d["occupied_agreement"]
                                                  for d in self.differences)
            entry["max_difference"] = {k: max(d[k] for d in self.differences)
                                       for k in self.differences[0]
                                       if not k.endswith("agreement")}
        return entry


@torch.no_grad()
def take_turns(variants: dict[str, Variant], sets, warmup: int, iters: int, cfg: ModelConfig,
               reference: Variant | None = None, progress: bool = True) -> int:
    """``warmup`` untimed steps, then ``iters`` timed steps taking turns with as many recorded
    by the marks (where a variant is eager), the variants one after the other on each camera
    set (``sets`` taken in turn, from the first again when they run out: the history
    restarts there, as when a bag loops); each variant's result compared with
    ``reference``'s (another variant, or one stepped here untimed). -> steps per variant."""
    marked = any(v.mode == "eager" for v in variants.values())
    schedule = ["warmup"] * warmup + (["timed", "marks"] if marked else ["timed"]) * iters
    extra = reference is not None and reference not in variants.values()
    for i, kind in enumerate(tqdm(schedule, desc=f"node step {cfg.name}",
                                  disable=not progress)):
        camera_set = sets[i % len(sets)]
        results = {name: v.step(camera_set, kind == "marks", kind != "warmup")
                   for name, v in variants.items()}
        if reference is None:
            continue
        expected = reference.step(camera_set, timed=False) if extra else \
            results[reference.name]
        for name, v in variants.items():
            v.differences.append(prediction_differences(results[name], expected, cfg))
    return len(schedule)


@torch.no_grad()
def bench_node_step(cfg: ModelConfig, device="cpu", modes=None, iters: int = 5,
                    warmup: int = 1, precisions=None, model: ODG | None = None,
                    progress: bool = True, sets=None, compiled_step=None,
                    frames: int | None = None, settings: dict | None = None) -> dict:
    """The node's step (module docstring) per variant: ``modes`` (None: the node's compile
    setting) x ``precisions`` (None: the node's), named by the mode, and the precision where
    several are asked for; ``take_turns`` runs them. ``sets``: camera sets as the node feeds
    them (default ``node_inputs``, random); ``settings``: ``node_settings()`` by default;
    ``frames``: history length (None: the model's); ``compiled_step``: a .pt2 of ``odg
    export --aoti`` that the compiled and graphs variants run instead of compiling."""
    settings = settings or node_settings()
    modes = tuple(modes or (settings["compile"],))
    # auto -> what the node runs on this device, so variants are named by what they compute
    precisions = tuple(dict.fromkeys(resolve_precision(p, device)
                                     for p in precisions or (settings["precision"],)))
    model = (model or ODG(cfg)).to(device).eval()
    if frames is not None and not 1 <= frames <= cfg.num_frames:
        raise ValueError(f"--frames must be in 1..{cfg.num_frames} for {cfg.name}")
    variants = {}
    for precision in precisions:
        for requested in modes:
            mode = resolve_mode(requested, device,
                                compiled_step is not None and requested != "eager")
            name = mode if len(precisions) == 1 else f"{mode}-{precision}"
            predictor = node_predictor(model, cfg, device, settings, mode, precision, frames,
                                       None if mode == "eager" else compiled_step)
            variants[name] = Variant(name, mode, precision, predictor)
    reference = next((v for v in variants.values()
                      if (v.mode, v.precision) == ("eager", "fp32")), None)
    extra = reference is None      # an untimed eager fp32 step: what the variants are against
    if extra:
        reference = Variant("eager-fp32", "eager", "fp32",
                            node_predictor(model, cfg, device, settings, "eager", "fp32",
                                           frames))
    if torch.device(device).type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    sets = sets or node_inputs(cfg, warmup + 2 * iters)
    steps = take_turns(variants, sets, warmup, iters, cfg, reference, progress)
    memory, method = peak_memory_mb(device)
    first = next(iter(variants.values()))
    reference_ms = statistics.median(first.times["step"])
    return {"preset": cfg.name, "device": str(device), "iters": iters, "warmup": warmup,
            "threads": torch.get_num_threads(), "torch": torch.__version__,
            "input": [cfg.num_cams, 3, *cfg.image_size],
            "frames": frames or cfg.num_frames, "steps": steps,
            "distinct_sets": min(len(sets), steps),
            "settings": {**settings, "padding": bool(cfg.occupancy_padding)},
            "precisions": list(precisions), "speedup_against": first.name,
            "reference": reference.name + (" (untimed)" if extra else ""),
            "modes": {name: v.result(cfg, reference_ms) for name, v in variants.items()},
            "peak_memory_mb": round(memory, 1), "memory_method": method}
