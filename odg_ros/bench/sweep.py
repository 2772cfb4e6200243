"""``odg bench --sweep``: speed against error, in one run, on one device.

Every configuration is a configuration of the node's step: an ``OnlinePredictor`` (history
length, query budget, precision, execution mode, visibility; or a model with fewer learned
queries, or another model) whose ``step`` is timed and scored over ``limit`` samples spread
evenly over a split. Per sample the predictor starts afresh and steps through the sample's
history frames (the dataset's, oldest first: untimed), then through the sample's own camera
set, timed ``repeats`` times (history again before each), plus once recorded by the step's
marks (online/marks.py: stages, decoder layers; eager configurations only, as ``odg bench``).
Its grid is scored (mIoU with the camera mask, RayIoU, mIoU over the moving classes) and its
boxes (mAP, ``metrics.detection``; every box ranked by score, as ``odg eval`` scores them).
The configurations take turns step by step in one process (a random order each round), so a
shared machine that gets busier during the sweep slows all of them alike. Reported per
configuration: median step time (what FPS is of) and its host and device parts, the stages
and decoder layers from the marks, the compile / capture time, peak memory, the scores, and
the same on the quietest and the busiest quarter of the samples (fewest / most occupied GT
voxels in the camera mask), so adaptive inference can be judged where it should help.

Peak memory: every configuration also runs alone in a fresh process (``isolate``: model,
first sample, warm-up + 1 step) and reports its peak resident set size (``ru_maxrss``:
interpreter + torch + weights + data + inference) on CPU, or
``torch.cuda.max_memory_allocated`` on CUDA.

Configurations derived from one checkpoint need no retraining: the history length is an
input, a query budget ranks the queries by the shipped keep-scores, and a smaller query set
keeps an evenly spaced subset of the learned queries (their decoder weights are shared).
Writes ``<out>/bench_<device>.json`` and ``.png`` (FPS against mIoU and RayIoU with the Pareto
front, and the latency breakdown).
"""
from __future__ import annotations

import dataclasses
import datetime
import json
import math
import multiprocessing
import os
import platform
import subprocess
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..network.precision import PRECISIONS
from ..online.step import MODES
from ..train.evaluate import add_box_list, dynamic_class_miou
from .step_timing import Variant, node_predictor, node_settings, peak_memory_mb

SUBSETS = ("all", "quiet", "busy")


@dataclass(frozen=True)
class SweepConfig:
    """One point of the sweep: a configuration of the node's step. frames: history length k
    incl. the current set (None: the model's); budget: the node's query_budget, "auto" or a
    fraction as text ("0.6"; network/budget.py: needs a checkpoint with trained budget heads,
    except random weights, which time it only), None: every query refined; precision: the
    node's precision (fp32 | bf16 | fp16); compile: the node's execution mode (eager |
    compiled | graphs, CUDA only); visibility: the node's visibility; queries: a model with
    this fraction of the learned queries, evenly spaced (``query_budget``); model: another
    checkpoint path or preset name (a preset: random weights, timing only) instead of the
    sweep's own model."""

    name: str
    frames: int | None = None
    budget: str | None = None
    precision: str = "fp32"
    compile: str = "eager"
    visibility: bool = True
    queries: float = 1.0
    model: str | None = None

    def __post_init__(self):
        if not 0 < self.queries <= 1:
            raise ValueError(f"{self.name}: queries must be a fraction in (0, 1]")
        if self.frames is not None and self.frames < 1:
            raise ValueError(f"{self.name}: frames must be >= 1")
        if self.compile not in MODES:
            raise ValueError(f"{self.name}: compile {self.compile!r}, expected one of {MODES}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"{self.name}: precision {self.precision!r}, expected one of "
                             f"{PRECISIONS}")

    def describe(self) -> str:
        """The name and the fields that differ from the defaults."""
        defaults = SweepConfig("")
        fields = [f"{f.name}={getattr(self, f.name)}" for f in dataclasses.fields(self)
                  if f.name != "name" and getattr(self, f.name) != getattr(defaults, f.name)]
        return f"{self.name:<18} {' '.join(fields)}".rstrip()


def default_configs(num_frames: int, device: str = "cpu") -> list[SweepConfig]:
    """History 1, 2, .., k; the learned query budgets (auto and the ladder's two smaller
    rungs: they need trained budget heads, as the shipped checkpoint has); fixed smaller
    query sets 1/2 and 1/4 (the tiny variants); bf16; on CUDA also fp16, the compiled step
    and the step replayed as a CUDA graph (the node's default there)."""
    k = num_frames
    histories = sorted({h for h in (1, 2, 4, 8) if h < k})
    configs = [SweepConfig(f"full-h{k}", frames=k)]
    configs += [SweepConfig(f"full-h{h}", frames=h) for h in histories]
    configs += [SweepConfig(f"budget-{name}-h{k}", frames=k, budget=name)
                for name in ("auto", "0.6", "0.35")]
    configs += [SweepConfig(f"q50-h{k}", frames=k, queries=0.5),
                SweepConfig(f"q25-h{k}", frames=k, queries=0.25),
                SweepConfig(f"bf16-h{k}", frames=k, precision="bf16")]
    if torch.device(device).type == "cuda":
        configs += [SweepConfig(f"fp16-h{k}", frames=k, precision="fp16"),
                    SweepConfig(f"compiled-h{k}", frames=k, compile="compiled"),
                    SweepConfig(f"compiled-bf16-h{k}", frames=k, compile="compiled",
                                precision="bf16"),
                    SweepConfig(f"graphs-h{k}", frames=k, compile="graphs"),
                    SweepConfig(f"graphs-bf16-h{k}", frames=k, compile="graphs",
                                precision="bf16")]
    return configs


def select_configs(spec: str | None, num_frames: int,
                   device: str = "cpu") -> list[SweepConfig]:
    """None: the defaults; a ``.json`` path: a list of SweepConfig fields; else
    comma-separated names of default configurations."""
    defaults = default_configs(num_frames, device)
    if spec is None:
        return defaults
    if spec.endswith(".json"):
        with open(spec) as f:
            items = json.load(f)
        if not isinstance(items, list) or not items:
            raise ValueError(f"{spec}: expected a non-empty JSON list of configurations")
        known = {f.name for f in dataclasses.fields(SweepConfig)}
        for item in items:
            unknown = set(item) - known
            if unknown:
                raise ValueError(f"{spec}: unknown keys {sorted(unknown)} (known: {sorted(known)})")
        return [SweepConfig(**item) for item in items]
    by_name = {c.name: c for c in defaults}
    names = [n.strip() for n in spec.split(",") if n.strip()]
    unknown = [n for n in names if n not in by_name]
    if unknown or not names:
        raise ValueError(f"unknown configurations {unknown}; known: {list(by_name)}")
    return [by_name[n] for n in names]


# ------------------------------------------------------------------------ model variants
def query_budget(model, cfg, fraction: float):
    """A model that keeps an evenly spaced ``fraction`` of the learned dynamic and static
    queries (at least one of each kind the model has); every other weight is shared."""
    from ..network import ODG

    D, S = cfg.dynamic_queries, cfg.static_queries
    d = max(1, round(D * fraction)) if D else 0
    s = max(1, round(S * fraction))
    keep_d = torch.linspace(0, D - 1, d).round().long() if d else torch.zeros(0, dtype=torch.long)
    keep_s = D + torch.linspace(0, S - 1, s).round().long()
    keep = torch.cat([keep_d, keep_s])
    new_cfg = cfg.replace(num_dynamic=d, num_static=s)
    state = model.state_dict()
    state["queries.features"] = state["queries.features"][keep]
    state["queries.init_points"] = state["queries.init_points"][keep]
    state["queries.init_box"] = state["queries.init_box"][keep_d]
    smaller = ODG(new_cfg)
    smaller.load_state_dict(state)
    return smaller.to(next(model.parameters()).device).eval(), new_cfg


def is_checkpoint(model: str) -> bool:
    """A ``SweepConfig.model`` names a checkpoint file, or a preset (name or YAML path)."""
    return Path(model).is_file() and Path(model).suffix not in (".yaml", ".yml")


def model_config(checkpoint, preset: str | None):
    """The ModelConfig of ``checkpoint`` (its weights are not built), else of ``preset``."""
    from ..model_config import ModelConfig, load_preset
    if checkpoint is None:
        return load_preset(preset)
    payload = torch.load(checkpoint, map_location="cpu", weights_only=False)
    return ModelConfig(**payload["config"])


def prepare_model(checkpoint, preset: str, device: str, config: SweepConfig):
    """-> (model on device in eval mode, its config) for one configuration."""
    from ..network.checkpoint import load_model

    if config.model is not None:
        checkpoint, preset = (config.model, preset) if is_checkpoint(config.model) else \
            (None, config.model)
    model, cfg = load_model(checkpoint, preset=preset, device="cpu")
    if config.frames is not None and config.frames > cfg.num_frames:
        raise ValueError(f"{config.name}: {config.frames} frames, the model takes at most "
                         f"{cfg.num_frames}")
    if config.queries < 1:
        model, cfg = query_budget(model, cfg, config.queries)
    if config.compile == "graphs" and torch.device(device).type != "cuda":
        raise ValueError(f"{config.name}: CUDA graphs need a CUDA device, not {device}")
    return model.to(device).eval(), cfg


def sample_camera_sets(sample: dict):
    """A dataset sample's frames as the node would have fed them: (the history frames'
    camera sets, oldest first, then the sample's own), each (uint8 images [N, H, W, 3],
    ego2img [N, 4, 4], pose, stamp). The poses are the ego warps inverted (frame 0 at the
    origin), so the predictor's warps are the sample's; a frame the dataset repeats (a scene's
    start) is fed once: the step repeats the oldest frame for the missing ones alike."""
    images, ego2img = sample["images"].numpy(), sample["ego2img"].double().numpy()
    warps = sample["ego_warp"].double().numpy()
    stamps = 1000.0 - sample["time_delta"].double().numpy()
    sets = []
    for t in reversed(range(len(stamps))):
        if sets and stamps[t] <= sets[-1][3]:
            continue
        sets.append((images[t], ego2img[t], np.linalg.inv(warps[t]), float(stamps[t])))
    return sets[:-1], sets[-1]


# ------------------------------------------------------------------------ the split
def scene_load(infos_path, cfg, occ_root, indices) -> list[dict]:
    """Per sample: occupied GT voxels inside the camera mask, all occupied voxels, GT boxes."""
    from ..data.dataset import OccDataset
    from ..data.occ_io import free_label_of

    dataset = OccDataset(infos_path, cfg, occ_root=occ_root)
    rows = []
    for index in indices:
        info = dataset.infos[index]
        semantics, _, mask_camera, has_occ = dataset.load_occupancy(info)
        occupied = semantics != free_label_of(dataset.dataset)
        rows.append({"index": index, "token": info["token"], "has_occ": bool(has_occ),
                     "occupied_camera": int((occupied & mask_camera).sum()),
                     "occupied": int(occupied.sum()), "boxes": int(len(info["gt_labels"]))})
    return rows


def spread_indices(count: int, limit: int) -> list[int]:
    """``limit`` sample indices spread evenly over a split of ``count`` (all if fewer): the
    first N samples would all come from the first scene or two."""
    if limit >= count:
        return list(range(count))
    return sorted({int(round(i)) for i in np.linspace(0, count - 1, limit)})


def quiet_and_busy(load: list[dict]) -> tuple[list[int], list[int]]:
    """The quarter of the samples (at least one) with the fewest / most occupied GT voxels
    in the camera mask (ties: fewer / more boxes), among samples with GT."""
    scored = [r for r in load if r["has_occ"]]
    if not scored:
        return [], []
    order = sorted(scored, key=lambda r: (r["occupied_camera"], r["boxes"], r["index"]))
    k = max(1, len(order) // 4)
    return [r["index"] for r in order[:k]], [r["index"] for r in order[-k:]]


# ------------------------------------------------------------------------ measuring
class ConfigRun:
    """One configuration during the measurement: its node step (``step.Variant``), the
    current sample's camera sets, the timings per sample, the scores."""

    def __init__(self, config: SweepConfig, job: dict):
        from ..metrics.detection import DetectionScore
        from ..metrics.score import OccScore

        self.config, self.device = config, job["device"]
        model, self.cfg = prepare_model(job["checkpoint"], job["preset"], self.device, config)
        self.frames = config.frames or self.cfg.num_frames
        self.random_weights = (config.model is None and job["checkpoint"] is None) or (
            config.model is not None and not is_checkpoint(config.model))
        if config.budget is not None and self.random_weights:
            model.decoder.budget_heads.set_trained(True)   # timing only: any ranking will do
        # the history is the dataset's (sample_camera_sets): kept as it comes; every box
        # ranked, none cut by the score threshold (mAP ranks them, as odg eval does)
        settings = node_settings(precision=config.precision, compile=config.compile,
                                 query_budget=config.budget or "full",
                                 visibility=config.visibility, history_interval=0.0,
                                 history_max_gap=math.inf)
        predictor = node_predictor(model, self.cfg.replace(box_score_threshold=0.0),
                                   self.device, settings, frames=self.frames)
        self.variant = Variant(config.name, predictor.mode, config.precision, predictor)
        self.scores = {name: OccScore(job["dataset"], rayiou=job.get("rayiou", True))
                       for name in SUBSETS}
        self.box_scores = {name: DetectionScore() for name in SUBSETS} \
            if self.cfg.dynamic_queries else None
        self.per_sample, self.error = [], None
        self.sample = self.history = self.current = self.prediction = None

    def begin_sample(self, sample: dict) -> None:
        self.sample, self.prediction = sample, None
        self.history, self.current = sample_camera_sets(sample)
        self.first_timed = len(self.variant.times["step"])

    def run_step(self, kind: str = "timed") -> None:
        """The sample's step after its history (untimed); ``kind``: timed, marks (recorded
        by the marks) or warmup."""
        predictor = self.variant.predictor
        predictor.reset()
        for camera_set in self.history:
            predictor.step(*camera_set)
        prediction = self.variant.step(self.current, kind == "marks", kind != "warmup")
        if kind == "timed" and self.prediction is None:
            self.prediction = prediction

    def end_sample(self, index: int, members: dict, origins) -> None:
        times = {k: v[self.first_timed:] for k, v in self.variant.times.items()}
        p, sample = self.prediction, self.sample
        self.per_sample.append({"index": index, "token": sample["token"],
                                "step_ms": round(float(np.median(times["step"])), 3),
                                "model_ms": round(float(np.median(times["model"])), 3),
                                "query_budget": p.query_budget,
                                "refined_fraction": round(p.refined_fraction, 4)})
        if self.box_scores is not None:
            for name in SUBSETS:
                if index in members[name]:
                    add_box_list(self.box_scores[name], p.boxes, sample["gt_boxes"],
                                 sample["gt_labels"], self.cfg)
        if sample["has_occ"]:
            gt = sample["occ_semantics"].numpy()
            mask = sample["occ_mask_camera"].numpy().astype(bool)
            ray_origins = origins(index) if origins is not None else None
            for name in SUBSETS:
                if index in members[name]:
                    self.scores[name].add(p.grid, gt, mask, ray_origins)
        self.sample = self.history = self.current = self.prediction = None

    def result(self, members: dict) -> dict:
        out = {"config": dataclasses.asdict(self.config), "model": self.cfg.name,
               "random_weights": self.random_weights,
               "queries": self.cfg.num_queries, "frames": self.frames,
               **self.variant.result(self.cfg), "per_sample": self.per_sample}
        for name in SUBSETS:
            out["scores" if name == "all" else name] = subset_result(
                self.scores[name], self.box_scores[name] if self.box_scores else None,
                self.per_sample, members[name])
        return out


def _rounds(runs: list[ConfigRun], kinds: list[str], order, progress) -> None:
    """Each kind of step in turn; in each, the runs in a new random order (no configuration
    always follows the same one: the one before leaves caches and the allocator in its own
    state). A configuration that fails stops there, the others go on."""
    for kind in kinds:
        active = [run for run in runs if run.error is None]
        if kind == "marks":                      # a compiled step has no marks to record
            active = [run for run in active if run.variant.mode == "eager"]
        for position in order.permutation(len(active)):
            run = active[position]
            try:
                run.run_step(kind)
            except Exception as error:
                run.error = failure(run.config, error)
            if kind == "timed":
                progress.update()


@torch.no_grad()
def measure_interleaved(configs: list[SweepConfig], job: dict) -> list[dict]:
    """Time and score every configuration in one process, interleaved: for each sample and
    repeat the configurations take turns (in a random order), so a machine that gets
    busier or quieter during the sweep slows every configuration alike."""
    from ..data.dataset import OccDataset
    from ..metrics.rayiou import LidarOrigins

    members = {"all": set(job["indices"]), "quiet": set(job["quiet"]),
               "busy": set(job["busy"])}
    runs, results = [], {}
    for config in configs:
        try:
            runs.append(ConfigRun(config, job))
        except Exception as error:  # one failing configuration must not lose the others
            results[config.name] = failure(config, error)
    datasets = {}
    origins = None
    order = np.random.default_rng(0)
    progress = tqdm(total=len(job["indices"]) * job["repeats"] * len(runs),
                    desc="sweep (interleaved steps)", disable=not job.get("progress", True))
    for sample_number, index in enumerate(job["indices"]):
        samples = {}
        for run in runs:
            if run.error is not None:
                continue
            try:
                if run.frames not in samples:
                    if run.frames not in datasets:
                        datasets[run.frames] = OccDataset(
                            job["data"], run.cfg.replace(num_frames=run.frames),
                            occ_root=job["occ_root"])
                        origins = origins or (LidarOrigins(datasets[run.frames].infos)
                                              if job.get("rayiou", True) else None)
                    samples[run.frames] = datasets[run.frames][index]
                run.begin_sample(samples[run.frames])
            except Exception as error:
                run.error = failure(run.config, error)
        warmup = ["warmup"] * job["warmup"] if sample_number == 0 else []
        _rounds(runs, warmup + ["timed"] * job["repeats"] + ["marks"], order, progress)
        for run in runs:
            if run.error is None:
                run.end_sample(index, members, origins)
    progress.close()
    for run in runs:
        results[run.config.name] = run.error or run.result(members)
    return [results[c.name] for c in configs]


def failure(config: SweepConfig, error: Exception) -> dict:
    return {"config": dataclasses.asdict(config), "error": f"{type(error).__name__}: {error}",
            "traceback": traceback.format_exc()}


@torch.no_grad()
def probe_memory(job: dict) -> dict:
    """Peak memory of one configuration: model, the first sample, ``warmup`` + 1 steps
    after its history -- run in a fresh process (``isolate``) so the figure is its own."""
    from ..data.dataset import OccDataset

    if job.get("threads"):
        torch.set_num_threads(job["threads"])
    config = SweepConfig(**job["config"])
    try:
        run = ConfigRun(config, job)
        after_load, _ = peak_memory_mb("cpu")
        dataset = OccDataset(job["data"], run.cfg.replace(num_frames=run.frames),
                             occ_root=job["occ_root"])
        run.begin_sample(dataset[job["indices"][0]])
        for _ in range(job["warmup"] + 1):
            run.run_step("warmup")
    except Exception as error:
        return failure(config, error)
    memory, method = peak_memory_mb(job["device"])
    return {"peak_memory_mb": round(memory, 1), "memory_method": method,
            "rss_after_load_mb": round(after_load, 1)
            if torch.device(job["device"]).type == "cpu" else None}


def subset_result(score, box_score, per_sample, members) -> dict:
    rows = [r for r in per_sample if r["index"] in members]
    out = {"samples": len(rows)}
    if rows:
        out["latency_ms"] = round(float(np.median([r["step_ms"] for r in rows])), 3)
        out["model_ms"] = round(float(np.median([r["model_ms"] for r in rows])), 3)
        out["refined_fraction"] = round(float(np.mean([r["refined_fraction"]
                                                        for r in rows])), 4)
    if score.miou.samples:
        res = score.result()
        out.update({k: res.get(k) for k in ("mIoU", "RayIoU", "IoU_geometry")})
        out["mIoU_dynamic"] = dynamic_class_miou(res)
    if box_score is not None and box_score.samples:
        out["box_mAP"] = box_score.result()["mAP"]
    return out


def _isolated(function, job: dict) -> dict:
    """Run ``function(job)`` in a fresh interpreter (spawn)."""
    context = multiprocessing.get_context("spawn")
    with context.Pool(1, maxtasksperchild=1) as pool:
        return pool.apply(function, (job,))


# ------------------------------------------------------------------------ the whole sweep
PARETO_TOLERANCE = 0.02   # score points: float noise between paths computing the same grid


def pareto_front(points: list[tuple[float, float]], tolerance: float = 0.0) -> list[int]:
    """Indices of the points no other point beats (higher is better in both coordinates, e.g.
    (FPS, mIoU)); equal points are all kept; None / NaN coordinates are out. A point beats
    another when it is at least as fast, at most ``tolerance`` worse in the score, and faster
    or more than ``tolerance`` better: float noise between two paths computing the same grid
    (plain vs fast path: 3e-4 to 3e-3 mIoU) must not keep the slower one on the front."""
    valid = [i for i, p in enumerate(points)
             if p[0] is not None and p[1] is not None and np.isfinite(p).all()]
    front = []
    for i in valid:
        xi, yi = points[i]
        dominated = any(points[j][0] >= xi and points[j][1] >= yi - tolerance
                        and (points[j][0] > xi or points[j][1] > yi + tolerance)
                        for j in valid)
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: points[i][0])


def pareto_report(results: list[dict]) -> dict:
    """{metric: config names on the (FPS, metric) front}, scores compared within
    PARETO_TOLERANCE; configs with random weights only when nothing else ran (their scores
    mean nothing)."""
    ok = [r for r in results if "error" not in r]
    trusted = [r for r in ok if not r["random_weights"]] or ok
    return {metric: [trusted[i]["config"]["name"] for i in pareto_front(
        [(r["fps"], r["scores"].get(metric)) for r in trusted], PARETO_TOLERANCE)]
        for metric in ("mIoU", "RayIoU")}


def git_commit() -> str:
    root = Path(__file__).resolve().parent.parent
    try:
        sha = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                             capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain",
                                "--untracked-files=no", "--", "odg_ros"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (sha + ("+local changes" if dirty else "")) if sha else "unknown"


def device_name(device: str) -> str:
    if torch.device(device).type == "cuda":
        return torch.cuda.get_device_name(device)
    try:
        with open("/proc/cpuinfo") as f:
            model = next((line.split(":", 1)[1].strip() for line in f
                          if line.startswith("model name")), platform.processor())
    except OSError:
        model = platform.processor() or "CPU"
    return f"{model} ({os.cpu_count()} cores)"


def run_sweep(data, checkpoint=None, preset: str = "odg_cpu", device: str = "cpu",
              configs: list[SweepConfig] | None = None, limit: int = 8, repeats: int = 3,
              warmup: int = 1, threads: int | None = None, isolate: bool | None = None,
              out=None, occ_root=None, rayiou: bool = True, progress: bool = True) -> dict:
    """Measure every configuration; write ``<out>/bench_<cpu|cuda>.json`` and ``.png`` when
    ``out`` is given. checkpoint None: random weights of ``preset`` (scores meaningless,
    flagged in the JSON and on the plot)."""
    from ..data.dataset import load_infos_file

    if torch.device(device).type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("odg bench --sweep: --device cuda but CUDA is not available here")
    if limit < 1 or repeats < 1 or warmup < 0:
        raise ValueError("limit and repeats must be >= 1, warmup >= 0")
    cfg = model_config(checkpoint, preset)
    configs = configs or default_configs(cfg.num_frames, device)
    isolate = True if isolate is None else isolate
    infos = load_infos_file(data)
    if not infos["infos"]:
        raise ValueError(f"{data}: no samples")
    indices = spread_indices(len(infos["infos"]), limit)
    load = scene_load(data, cfg, occ_root, indices)
    quiet, busy = quiet_and_busy(load)
    meta = sweep_meta(device, threads, checkpoint, cfg, data, indices, repeats, warmup, isolate)
    meta.update(scene_load=load, quiet_samples=quiet, busy_samples=busy)
    base = {"checkpoint": str(checkpoint) if checkpoint else None, "preset": preset,
            "dataset": infos["dataset"],
            "device": device, "data": str(data), "occ_root": occ_root, "indices": indices,
            "quiet": quiet, "busy": busy, "repeats": repeats, "warmup": warmup,
            "threads": threads, "rayiou": rayiou, "progress": progress}
    memory = {}
    for config in tqdm(configs, desc="sweep: peak memory, one process each" if isolate else
                       "sweep: memory", disable=not progress):
        job = {**base, "config": dataclasses.asdict(config)}
        memory[config.name] = _isolated(probe_memory, job) if isolate else probe_memory(job)
    if threads:
        torch.set_num_threads(threads)
    runnable = [c for c in configs if "error" not in memory[c.name]]
    measured = iter(measure_interleaved(runnable, base) if runnable else [])
    results = []
    for config in configs:
        result = memory[config.name] if config not in runnable else \
            {**next(measured), **memory[config.name]}
        if "error" in result:
            tqdm.write(f"sweep: {config.name} failed: {result['error']}")
        results.append(result)
    meta["load_average_after"] = list(os.getloadavg())
    ok = [r for r in results if "error" not in r]
    if not ok:
        raise RuntimeError("every sweep configuration failed: "
                           + "; ".join(r["error"] for r in results))
    report = {"meta": meta, "configs": results, "pareto": pareto_report(results)}
    if out is not None:
        report["files"] = write_sweep(report, Path(out), device)
    return report


def sweep_meta(device, threads, checkpoint, cfg, data, indices, repeats, warmup,
               isolate) -> dict:
    """What a sweep's numbers were measured on and how (the report's ``meta``)."""
    return {"device": device, "device_name": device_name(device),
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "commit": git_commit(), "torch": torch.__version__,
            "threads": threads or torch.get_num_threads(),
            # libgomp's default busy-waiting makes 2 threads ~9x slower on a loaded 2-core CPU
            "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
            "checkpoint": str(checkpoint) if checkpoint else None,
            "random_weights": checkpoint is None, "preset": cfg.name,
            "data": str(data), "samples": len(indices), "repeats": repeats, "warmup": warmup,
            "isolated_processes": isolate, "load_average_before": list(os.getloadavg()),
            "memory_method": ("torch.cuda.max_memory_allocated" if torch.device(device).type
                              == "cuda" else "ru_maxrss (interpreter, torch, weights, data "
                              "and inference together)")
            + (" of a fresh process per configuration (model, first sample, warm-up + 1 "
               "step after its history)" if isolate else
               " of this process: a RUNNING MAXIMUM over the configurations, not their own"),
            "latency": "the node's step (OnlinePredictor.step: upload, backbone on the "
                       "newest set, decoder over the feature ring, grid with padding, boxes, "
                       "visibility, download), median over samples x repeats, each after "
                       "the sample's history; stages and decoder layers from the step's marks "
                       "on steps of their own (eager configurations); the configurations "
                       "take turns step by step in one process"}


def write_sweep(report: dict, out: Path, device) -> list[str]:
    """``<out>/bench_<cpu|cuda>.json`` and ``.png``; -> their paths."""
    from .plots import plot_sweep
    out.mkdir(parents=True, exist_ok=True)
    stem = f"bench_{torch.device(device).type}"
    with open(out / f"{stem}.json", "w") as f:
        json.dump(report, f, indent=1)
    plot_sweep(report, out / f"{stem}.png")
    return [str(out / f"{stem}.json"), str(out / f"{stem}.png")]


# ------------------------------------------------------------------------ report
def format_sweep_table(report: dict) -> str:
    lines = [f"{'config':<18} {'FPS':>6} {'step':>7} {'model':>7} {'backbone':>8} "
             f"{'decoder':>7} {'post':>6} {'mem MB':>7} {'mIoU':>6} {'RayIoU':>6} "
             f"{'mIoU_dyn':>8} {'box mAP':>7} {'quiet ms':>8} {'busy ms':>8} {'queries':>7} "
             f"{'refined':>7} {'start s':>7}"]
    cell = lambda v, f="{:.2f}": "-" if v is None else f.format(v)  # noqa: E731
    for r in report["configs"]:
        name = r["config"]["name"]
        if "error" in r:
            lines.append(f"{name:<18} FAILED: {r['error']}")
            continue
        lat, s = r["latency_ms"], r["scores"]
        lines.append(
            f"{name:<18} {cell(r['fps']):>6} {cell(lat['step'], '{:.1f}'):>7} "
            f"{cell(lat['model'], '{:.1f}'):>7} {cell(lat.get('backbone'), '{:.1f}'):>8} "
            f"{cell(lat.get('decoder'), '{:.1f}'):>7} "
            f"{cell(lat.get('postprocess'), '{:.1f}'):>6} "
            f"{cell(r['peak_memory_mb'], '{:.0f}'):>7} "
            f"{cell(s.get('mIoU')):>6} {cell(s.get('RayIoU')):>6} "
            f"{cell(s.get('mIoU_dynamic')):>8} {cell(s.get('box_mAP')):>7} "
            f"{cell(r['quiet'].get('latency_ms'), '{:.1f}'):>8} "
            f"{cell(r['busy'].get('latency_ms'), '{:.1f}'):>8} {r['queries']:>7} "
            f"{cell(s.get('refined_fraction'), '{:.0%}'):>7} "
            f"{cell(r['startup_s'], '{:.1f}'):>7}")
    lines.append("step: the node's whole step per camera set (FPS = 1000 / step); model: its "
                 "device part; backbone, decoder, post: the step's marks (eager rows; - where "
                 "a compiled or graph-replayed step has none)")
    for metric, names in report["pareto"].items():
        lines.append(f"Pareto front (FPS, {metric}): {', '.join(names)}")
    return "\n".join(lines)
