"""``odg bench --sweep``: speed against error, in one run, on one device.

For each configuration (history length, query budget, precision, sampling path) the online
step of the node runs over ``limit`` samples spread evenly over a split: the older frames'
features are computed first (the node has them cached), then the step -- backbone on the
newest set, decoder over the cached history, grid + boxes -- is timed ``repeats`` times per
sample after ``warmup`` steps, and its grid is scored (mIoU with the camera mask, RayIoU,
mIoU over the moving classes) and its boxes (mAP, ``metrics.detection``). The
configurations take turns step by step in one process (a random order each round), so a
shared machine that gets busier during the sweep slows all of them alike. Reported per
configuration: median latency per stage, per decoder layer and per part of a layer, FPS, peak
memory, the scores, and the same on the quietest and the busiest quarter of the samples
(fewest / most occupied GT voxels in the camera mask), so adaptive inference can be judged
where it should help.

Peak memory: every configuration also runs alone in a fresh process (``isolate``: model,
first sample, its history, warm-up + 1 step) and reports its peak resident set size
(``ru_maxrss``: interpreter + torch + weights + data + inference) on CPU, or
``torch.cuda.max_memory_allocated`` on CUDA.

Configurations derived from one checkpoint need no retraining: the history length is an
input, and a query budget keeps an evenly spaced subset of the learned queries (their
decoder weights are shared). Writes ``<out>/bench_<device>.json`` and ``.png`` (FPS
against mIoU and RayIoU with the Pareto front, and the latency breakdown).
"""
from __future__ import annotations

import dataclasses
import datetime
import json
import multiprocessing
import os
import platform
import subprocess
import traceback
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..network.budget import output_needs
from .step import DecoderHooks, TimedOnlineStep, StageTimer, peak_memory_mb, summarise
from ..train.evaluate import add_box_sample, dynamic_class_miou

SUBSETS = ("all", "quiet", "busy")


@dataclass(frozen=True)
class SweepConfig:
    """One point of the sweep. frames: history length k incl. the current set (None: the
    model's); queries: fraction of the learned queries kept; precision: fp32 | bf16 | fp16
    (autocast); ring: cached history in a ``FeatureRing`` (else re-laid out every step);
    fast_sampling: camera-rows sampling (else the plain 3-D path); compile: torch.compile
    the decoder (per-layer timing is then off: hooks would break the graph); cuda_graphs:
    compiled with mode "reduce-overhead", which replays the decoder's kernels as CUDA graphs
    (CUDA only: one launch instead of thousands of small ones); model: another
    checkpoint path or preset name (a preset: random weights, timing only) instead of the
    sweep's own model; budget: the node's query_budget, "auto" or a fraction as text
    ("0.6"; network/budget.py: the learned keep-score chooses the refined queries; needs a
    checkpoint with trained budget heads, except random weights, which time it only), None:
    every query refined."""

    name: str
    frames: int | None = None
    queries: float = 1.0
    precision: str = "fp32"
    ring: bool = True
    fast_sampling: bool = True
    compile: bool = False
    cuda_graphs: bool = False
    model: str | None = None
    budget: str | None = None

    @property
    def compiled(self) -> bool:
        return self.compile or self.cuda_graphs

    def __post_init__(self):
        if not 0 < self.queries <= 1:
            raise ValueError(f"{self.name}: queries must be a fraction in (0, 1]")
        if self.frames is not None and self.frames < 1:
            raise ValueError(f"{self.name}: frames must be >= 1")


def default_configs(num_frames: int, device: str = "cpu") -> list[SweepConfig]:
    """History 1, 2, .., k; the learned query budgets (auto and the ladder's two smaller
    rungs: they need trained budget heads, as the shipped checkpoint has); fixed smaller
    query sets 1/2 and 1/4 (the tiny variants); bf16 autocast; the plain path; on CUDA also
    fp16, torch.compile and CUDA graphs."""
    k = num_frames
    histories = sorted({h for h in (1, 2, 4, 8) if h < k})
    configs = [SweepConfig(f"full-h{k}", frames=k)]
    configs += [SweepConfig(f"full-h{h}", frames=h) for h in histories]
    configs += [SweepConfig(f"budget-{name}-h{k}", frames=k, budget=name)
                for name in ("auto", "0.6", "0.35")]
    configs += [SweepConfig(f"q50-h{k}", frames=k, queries=0.5),
                SweepConfig(f"q25-h{k}", frames=k, queries=0.25),
                SweepConfig(f"bf16-h{k}", frames=k, precision="bf16"),
                SweepConfig(f"plain-h{k}", frames=k, ring=False, fast_sampling=False)]
    if torch.device(device).type == "cuda":
        configs += [SweepConfig(f"fp16-h{k}", frames=k, precision="fp16"),
                    SweepConfig(f"compile-h{k}", frames=k, compile=True),
                    SweepConfig(f"compile-bf16-h{k}", frames=k, compile=True,
                                precision="bf16"),
                    SweepConfig(f"graphs-h{k}", frames=k, cuda_graphs=True),
                    SweepConfig(f"graphs-bf16-h{k}", frames=k, cuda_graphs=True,
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
    smaller.fast_sampling = model.fast_sampling
    return smaller.to(next(model.parameters()).device).eval(), new_cfg


def is_checkpoint(model: str) -> bool:
    """A ``SweepConfig.model`` names a checkpoint file, or a preset (name or YAML path)."""
    return Path(model).is_file() and Path(model).suffix not in (".yaml", ".yml")


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
    if config.cuda_graphs and torch.device(device).type != "cuda":
        raise ValueError(f"{config.name}: CUDA graphs need a CUDA device, not {device}")
    model.fast_sampling = config.fast_sampling
    model = model.to(device).eval()
    if config.compiled:
        model.decoder = torch.compile(
            model.decoder, mode="reduce-overhead" if config.cuda_graphs else "default")
    return model, cfg


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
    """One configuration during the measurement: its model, online step, timers, scores."""

    def __init__(self, config: SweepConfig, job: dict):
        from ..metrics.detection import DetectionScore
        from ..metrics.score import OccScore

        self.config, self.device = config, job["device"]
        self.model, self.cfg = prepare_model(job["checkpoint"], job["preset"], self.device,
                                             config)
        self.frames = config.frames or self.cfg.num_frames
        self.random_weights = (config.model is None and job["checkpoint"] is None) or (
            config.model is not None and not is_checkpoint(config.model))
        self.step = TimedOnlineStep(self.model, self.cfg, self.device, ring=config.ring,
                                    precision=config.precision)
        self.scores = {name: OccScore(job["dataset"], rayiou=job.get("rayiou", True))
                       for name in SUBSETS}
        self.box_scores = {name: DetectionScore() for name in SUBSETS} \
            if self.cfg.dynamic_queries else None
        self.budgets = self.policy = None
        if config.budget is not None:
            from ..online.predictor import resolve_budget
            if self.random_weights:         # timing only: any ranking costs a budget alike
                self.model.decoder.budget_heads.set_trained(True)
            self.budgets, self.policy = resolve_budget(config.budget, self.model, self.cfg)
        self.timer, self.per_sample, self.error = StageTimer(self.device), [], None
        self.history = self.sample_timer = self.output = self.grid = None

    def begin_sample(self, batch) -> None:
        """The older frames' features (the node has them cached): untimed."""
        images = batch["images"]
        self.batch = batch
        self.history = [self.step.features(images[:, t]) for t in range(1, images.shape[1])]
        self.sample_timer = StageTimer(self.device)
        if self.budgets is not None:     # auto: chosen from the sample before (the policy's)
            self.step.budget = self.policy.budget if self.policy else self.budgets[0]

    def run_step(self, timer: StageTimer | None = None) -> None:
        b = self.batch
        self.step.prime(self.history)
        timer = timer or self.sample_timer
        with DecoderHooks(self.model, timer) if not self.config.compiled else nullcontext():
            output, self.grid, _ = self.step(b["images"][:, 0], b["ego2img"], b["ego_warp"],
                                             b["time_delta"], timer)
        timer.flush()
        # scored in end_sample, after the other configurations' steps: a compiled decoder's
        # outputs may be CUDA-graph buffers by then overwritten (seen on an H100: graphs-h4
        # box mAP 0.76 against 18.54; the grid, computed in the step, was right)
        self.output = output.cloned() if self.config.compiled else output

    def end_sample(self, index: int, members: dict, origins) -> None:
        for name, values in self.sample_timer.times.items():
            self.timer.times.setdefault(name, []).extend(values)
        medians = self.sample_timer.medians()
        last = self.output.last
        budget = self.step.budget
        refined = 1.0 if budget is None else budget.refined_fraction(self.cfg)
        if self.policy is not None:
            self.policy.update(*output_needs(self.output, self.model, self.cfg))
        self.per_sample.append({"index": index, "token": self.batch["token"][0],
                                "total_ms": round(medians["total"], 3),
                                "decoder_ms": round(medians["decoder"], 3),
                                "queries_last_layer": int(last.means.shape[1]),
                                "refined_fraction": round(refined, 4),
                                "gaussians_last_layer": int(last.means.shape[1]
                                                            * last.means.shape[2])})
        if self.box_scores is not None:
            for name in SUBSETS:
                if index in members[name]:
                    add_box_sample(self.box_scores[name], self.output, self.batch, self.cfg)
        if self.batch["has_occ"][0]:
            pred = self.grid[0].cpu().numpy()
            gt = self.batch["occ_semantics"][0].cpu().numpy()
            mask = self.batch["occ_mask_camera"][0].cpu().numpy().astype(bool)
            ray_origins = origins(index) if origins is not None else None
            for name in SUBSETS:
                if index in members[name]:
                    self.scores[name].add(pred, gt, mask, ray_origins)
        self.history = self.batch = self.output = self.grid = None

    def result(self, members: dict) -> dict:
        out = {"config": dataclasses.asdict(self.config), "model": self.cfg.name,
               "random_weights": self.random_weights,
               "queries": self.cfg.num_queries, "frames": self.frames,
               **summarise(self.timer, self.cfg.num_layers), "per_sample": self.per_sample}
        for name in SUBSETS:
            out["scores" if name == "all" else name] = subset_result(
                self.scores[name], self.box_scores[name] if self.box_scores else None,
                self.per_sample, members[name])
        return out


@torch.no_grad()
def measure_interleaved(configs: list[SweepConfig], job: dict) -> list[dict]:
    """Time and score every configuration in one process, interleaved: for each sample and
    repeat the configurations take turns (in a random order), so a machine that gets
    busier or quieter during the sweep slows every configuration alike."""
    from ..data.batch import collate, to_device
    from ..data.dataset import OccDataset
    from ..metrics.rayiou import LidarOrigins

    device = job["device"]
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
    # a new random order every round: no configuration always follows the same one (the
    # one before leaves caches and the allocator in its own state)
    order = np.random.default_rng(0)
    progress = tqdm(total=len(job["indices"]) * job["repeats"] * len(runs),
                    desc="sweep (interleaved steps)", disable=not job.get("progress", True))
    for sample_number, index in enumerate(job["indices"]):
        batches = {}
        for run in runs:
            if run.error is not None:
                continue
            try:
                if run.frames not in batches:
                    if run.frames not in datasets:
                        datasets[run.frames] = OccDataset(
                            job["data"], run.cfg.replace(num_frames=run.frames),
                            occ_root=job["occ_root"])
                        origins = origins or (LidarOrigins(datasets[run.frames].infos)
                                              if job.get("rayiou", True) else None)
                    batches[run.frames] = to_device(
                        collate([datasets[run.frames][index]]), device)
                run.begin_sample(batches[run.frames])
                if sample_number == 0:
                    for _ in range(job["warmup"]):
                        run.run_step(StageTimer(device))
            except Exception as error:
                run.error = failure(run.config, error)
        for repeat in range(job["repeats"]):
            active = [run for run in runs if run.error is None]
            for position in order.permutation(len(active)):
                run = active[position]
                try:
                    run.run_step()
                except Exception as error:
                    run.error = failure(run.config, error)
                progress.update()
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
    """Peak memory of one configuration: model, the first sample, its cached history,
    ``warmup`` + 1 steps -- run in a fresh process (``isolate``) so the figure is its own."""
    from ..data.batch import collate, to_device
    from ..data.dataset import OccDataset

    if job.get("threads"):
        torch.set_num_threads(job["threads"])
    config = SweepConfig(**job["config"])
    try:
        run = ConfigRun(config, job)
        after_load, _ = peak_memory_mb("cpu")
        dataset = OccDataset(job["data"], run.cfg.replace(num_frames=run.frames),
                             occ_root=job["occ_root"])
        run.begin_sample(to_device(collate([dataset[job["indices"][0]]]), job["device"]))
        for _ in range(job["warmup"] + 1):
            run.run_step(StageTimer(job["device"]))
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
        out["latency_ms"] = round(float(np.median([r["total_ms"] for r in rows])), 3)
        out["decoder_ms"] = round(float(np.median([r["decoder_ms"] for r in rows])), 3)
        out["queries_last_layer"] = round(float(np.mean([r["queries_last_layer"]
                                                          for r in rows])), 1)
        out["refined_fraction"] = round(float(np.mean([r.get("refined_fraction", 1.0)
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
    from ..config import load_preset
    from ..data.dataset import load_infos_file

    if torch.device(device).type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("odg bench --sweep: --device cuda but CUDA is not available here")
    if limit < 1 or repeats < 1 or warmup < 0:
        raise ValueError("limit and repeats must be >= 1, warmup >= 0")
    if checkpoint is None:
        cfg = load_preset(preset)
    else:
        from ..config import ModelConfig
        payload = torch.load(checkpoint, map_location="cpu", weights_only=False)
        cfg = ModelConfig(**payload["config"])
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
            + (" of a fresh process per configuration (model, first sample, its history, "
               "warm-up + 1 step)" if isolate else
               " of this process: a RUNNING MAXIMUM over the configurations, not their own"),
            "latency": "median over samples x repeats of the online step (backbone on the "
                       "newest set, decoder over the cached history, grid + boxes); the "
                       "configurations take turns step by step in one process"}


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
    lines = [f"{'config':<16} {'FPS':>6} {'total':>8} {'backbone':>8} {'decoder':>8} "
             f"{'post':>6} {'mem MB':>7} {'mIoU':>6} {'RayIoU':>6} {'mIoU_dyn':>8} {'box mAP':>7} "
             f"{'quiet ms':>8} {'busy ms':>8} {'Q last':>6} {'refined':>7}"]
    cell = lambda v, f="{:.2f}": "-" if v is None else f.format(v)  # noqa: E731
    for r in report["configs"]:
        name = r["config"]["name"]
        if "error" in r:
            lines.append(f"{name:<16} FAILED: {r['error']}")
            continue
        lat, s = r["latency_ms"], r["scores"]
        lines.append(
            f"{name:<16} {cell(r['fps']):>6} {cell(lat['total'], '{:.1f}'):>8} "
            f"{cell(lat['backbone'], '{:.1f}'):>8} {cell(lat['decoder'], '{:.1f}'):>8} "
            f"{cell(lat['postprocess'], '{:.1f}'):>6} {cell(r['peak_memory_mb'], '{:.0f}'):>7} "
            f"{cell(s.get('mIoU')):>6} {cell(s.get('RayIoU')):>6} "
            f"{cell(s.get('mIoU_dynamic')):>8} {cell(s.get('box_mAP')):>7} "
            f"{cell(r['quiet'].get('latency_ms'), '{:.1f}'):>8} "
            f"{cell(r['busy'].get('latency_ms'), '{:.1f}'):>8} "
            f"{cell(s.get('queries_last_layer'), '{:.0f}'):>6} "
            f"{cell(s.get('refined_fraction'), '{:.0%}'):>7}")
    for metric, names in report["pareto"].items():
        lines.append(f"Pareto front (FPS, {metric}): {', '.join(names)}")
    return "\n".join(lines)
