"""Latency of one online step: backbone on the newest frame, decoder over K cached frames,
post-processing. Random weights and random images at the preset's resolution."""
from __future__ import annotations

import statistics
import time
from contextlib import contextmanager

import torch
from tqdm import tqdm

from .config import ModelConfig
from .network import ODG
from .network.postprocess import box_list, occupancy_grid
from .rig import ring_ego2img


def online_inputs(cfg: ModelConfig, frames: int, device, seed: int = 0):
    """Random current images and geometry of a car driving 10 m/s straight ahead."""
    g = torch.Generator().manual_seed(seed)
    H, W = cfg.image_size
    images = torch.randn(1, cfg.num_cams, 3, H, W, generator=g).to(device)
    ego2img = ring_ego2img(cfg.image_size, frames, cfg.num_cams).to(device)
    time_delta = torch.arange(frames, dtype=torch.float32, device=device)[None] * 0.5
    ego_warp = torch.eye(4, device=device).repeat(1, frames, 1, 1)
    ego_warp[0, :, 0, 3] = 10.0 * time_delta[0]  # the past ego was behind: x_past = x + v dt
    return images, ego2img, ego_warp, time_delta


class StageTimer:
    """Wall-clock per stage; on CUDA with events so no host sync sits inside a stage."""

    def __init__(self, device):
        self.cuda = torch.device(device).type == "cuda"
        self.times: dict[str, list[float]] = {}
        self._pending = []

    @contextmanager
    def stage(self, name: str):
        if self.cuda:
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            yield
            end.record()
            self._pending.append((name, start, end))
        else:
            t0 = time.perf_counter()
            yield
            self.times.setdefault(name, []).append((time.perf_counter() - t0) * 1e3)

    def flush(self):
        if self._pending:
            torch.cuda.synchronize()
            for name, start, end in self._pending:
                self.times.setdefault(name, []).append(start.elapsed_time(end))
            self._pending.clear()

    def medians(self) -> dict[str, float]:
        self.flush()
        return {k: statistics.median(v) for k, v in self.times.items()}


@torch.no_grad()
def bench_online_step(cfg: ModelConfig, device="cpu", frames: int | None = None, iters: int = 5,
                      warmup: int = 1, progress: bool = True) -> dict:
    frames = frames or cfg.num_frames
    if not 1 <= frames <= cfg.num_frames:
        raise ValueError(f"--frames must be in 1..{cfg.num_frames} for {cfg.name}")
    model = ODG(cfg).to(device).eval()
    images, ego2img, ego_warp, time_delta = online_inputs(cfg, frames, device)
    cached = model.extract_features(images)  # stands in for the k-1 cached history frames
    timer = StageTimer(device)
    for i in tqdm(range(warmup + iters), desc=f"bench {cfg.name}", disable=not progress):
        if i == warmup:
            timer = StageTimer(device)
        with timer.stage("total"):
            with timer.stage("backbone"):
                current = model.extract_features(images)
            with timer.stage("decoder"):
                output = model.decode([current] + [cached] * (frames - 1), ego2img, ego_warp,
                                      time_delta)
            with timer.stage("postprocess"):
                occupancy_grid(output, cfg)
                box_list(output, cfg)
        timer.flush()
    latency = timer.medians()
    return {"preset": cfg.name, "device": str(device), "frames": frames, "iters": iters,
            "input": [cfg.num_cams, 3, *cfg.image_size], "threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "latency_ms": {k: round(latency[k], 2)
                           for k in ("backbone", "decoder", "postprocess", "total")},
            "fps": round(1000.0 / latency["total"], 2)}
