"""Training loop of ODG (docs/architecture.md sec. 5).

AdamW (lr 2e-4, weight decay 0.01, backbone lr x 0.1), warm-up + cosine schedule, gradient
clipping at 35, mixed precision on CUDA, atomic checkpoints with optimizer and scheduler
state, ``resume``, a tqdm bar and a CSV log of every loss term. A resumed run is the run never
stopped, to the last bit on CPU: the checkpoint holds every process's random-number state
(dropout, render pixels) and a fresh loader worker replays the history-interval draws of the
samples before it (exact with 0 or 1 loader workers; with more, the workers are dealt other
batches after a resume and the intervals differ).

The host does not wait for the device within a step (the criterion's checks aside). A step
whose loss or gradient is not finite is skipped on the device: the fused AdamW kernel gets the
flag as GradScaler's ``found_inf`` and leaves weights, moments and step counts as they were,
and BatchNorm statistics, where BatchNorm trains, go back by ``torch.where``. The learning-rate
schedule advances on every step, skipped or not (GradScaler's convention: the host cannot know
which steps were skipped without waiting). Each step's loss terms, gradient norm and skip flag
stay on the device until one stacked copy brings ``log_every`` steps of them to the host;
skipped steps are counted and reported then.

Distributed: started by ``torchrun`` (env WORLD_SIZE/RANK/LOCAL_RANK), torch DDP with gloo on
CPU and NCCL on CUDA. The skip flag is all-reduced on the device so every rank skips the same
steps.
"""
from __future__ import annotations

import csv
import errno
import functools
import gc
import importlib.util
import logging
import math
import os
import random
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm

from ..model_config import ModelConfig
from ..data.augment import augment_batch
from ..data.batch import collate, to_device
from ..data.dataset import OccDataset, replay_history_draws
from ..data.prefetch import DevicePrefetcher
from ..losses.criterion import ODGCriterion
from ..network import ODG
from ..network.backbone_weights import backbone_start, load_backbone_weights
from ..network.checkpoint import load_weights, read_checkpoint, save_checkpoint, tensor_bytes
from ..training_phases import training_phase
from .schedule import warmup_cosine

log = logging.getLogger(__name__)


@dataclass
class TrainOptions:
    out_dir: Path
    epochs: int = 24
    max_steps: int | None = None          # stop early (smoke runs, budgets)
    batch_size: int = 1                   # per process
    lr: float = 2e-4
    weight_decay: float = 0.01
    backbone_lr_mult: float = 0.1
    warmup_steps: int = 200
    grad_clip: float = 35.0
    workers: int = 2
    seed: int = 0
    render: bool = True
    render_pixels_per_camera: int = 512
    renderer: str = "auto"                # gsplat's CUDA rasteriser where it can run, else ours
    history_grad: bool = True             # False: no backbone gradient through past frames
    augment: bool = True                  # flip, resize-and-crop, photometric (data/augment.py)
    checkpoint_backbone: bool = False     # recompute the backbone in the backward (memory)
    compile: bool = False                 # torch.compile the model's forward
    checkpoint_every: int = 500
    log_every: int = 10                   # steps between reads of the losses from the device
    device: str = "auto"
    backbone_weights: str | None = None   # ResNet checkpoint (network/backbone_weights.py)
    backbone_from_scratch: bool = False   # unfreeze a preset's frozen backbone (no weights)
    init_checkpoint: str | None = None    # start from these weights (not a resume)
    resume: bool = False
    progress: bool = True
    extra: dict = field(default_factory=dict)


def distributed_context():
    """(rank, world_size, local_rank); initialises the process group under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        dist.init_process_group(backend)
    rank = dist.get_rank() if dist.is_initialized() else 0
    return rank, world, int(os.environ.get("LOCAL_RANK", "0"))


def end_distributed() -> None:
    """Frees the process group while the interpreter is still whole: left to its shutdown,
    gloo's worker threads can abort a finished run (SIGABRT, "terminate called without an
    active exception"). Destroying the group only drops torch's own references; the DDP
    wrapper holds it too, and a Trainer sits in reference cycles, so the caller must have let
    go of its Trainer and the cycles are collected here."""
    gc.collect()
    if dist.is_initialized():
        dist.destroy_process_group()


def process_device(name: str, local_rank: int) -> torch.device:
    """``auto``: this process's GPU (its torchrun local rank) when CUDA is there, else the CPU;
    a bare ``cuda`` means this process's GPU too, ``cuda:N`` GPU N."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(name)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", local_rank)
    return device


def training_renderer(name: str, device: torch.device):
    """The render loss's renderer: ``torch`` ours (None: the criterion's default), ``gsplat``
    gsplat's rasteriser, which has CUDA kernels only; ``auto`` gsplat on CUDA when it is
    installed (its kernels size their work on the device; ours reads sizes back), else ours."""
    if name == "auto":
        name = "gsplat" if device.type == "cuda" and importlib.util.find_spec("gsplat") \
            else "torch"
    if name == "torch":
        return None
    if name != "gsplat":
        raise ValueError(f"renderer must be auto, torch or gsplat, got {name!r}")
    if device.type != "cuda":
        raise ValueError(f"--renderer gsplat needs a CUDA device (gsplat's rasteriser has no "
                         f"CPU kernels); this run is on {device}")
    try:
        import gsplat  # noqa: F401
    except ImportError as error:
        raise ValueError("--renderer gsplat needs gsplat (pip install gsplat==1.5.3)") \
            from error
    from ..render.gsplat_backend import render_scenes_gsplat
    return render_scenes_gsplat


def channels_last_convolutions(model: ODG) -> None:
    """Backbone and FPN weights in channels-last memory, the layout their inputs and
    features have (ODG.extract_features): cuDNN then runs NHWC kernels without re-laying
    out each weight and its gradient in every step. Values are unchanged."""
    model.backbone.to(memory_format=torch.channels_last)
    model.neck.to(memory_format=torch.channels_last)


def checkpoint_backbone(model: ODG) -> None:
    """The backbone stages that train keep only their inputs for the backward pass and run
    again in it (gradient checkpointing): less activation memory, one more backbone forward.
    Refused where BatchNorm trains: the second forward would update its statistics twice."""
    if not model.backbone.norm_eval:
        raise ValueError("--checkpoint-backbone needs a backbone with frozen BatchNorm "
                         "(norm_eval, as with pretrained weights): this one trains its "
                         "BatchNorm statistics, which the recomputation would update twice")
    model.backbone.checkpoint_stages = True


def zero_weight_anchor(output) -> torch.Tensor:
    """0 x (every output tensor): each parameter gets a (possibly zero) gradient on every rank
    even when a term is empty on it (no LiDAR pixel -> Phi unused), so DDP's all-reduce sees
    the same parameters everywhere. NaN outputs still make the step non-finite (skipped)."""
    total = output.init_means.sum() * 0.0
    for layer in output.layers:
        for t in (layer.means, layer.logits, layer.scales, layer.rotations, layer.opacities,
                  layer.boxes, layer.box_logits):
            if t is not None:
                total = total + t.float().sum() * 0.0
    return total


def parameter_groups(model: ODG, opts: TrainOptions) -> list[dict]:
    backbone = [p for p in model.backbone.parameters() if p.requires_grad]
    ids = {id(p) for p in backbone}
    rest = [p for p in model.parameters() if p.requires_grad and id(p) not in ids]
    return [{"params": backbone, "lr": opts.lr * opts.backbone_lr_mult, "name": "backbone"},
            {"params": rest, "lr": opts.lr, "name": "rest"}]


def training_dataset(infos, cfg: ModelConfig) -> torch.utils.data.Dataset:
    """One OccDataset per infos file, concatenated: each keeps its own dataroot, and a
    sample's history is looked up in its own file, so scene names may repeat across files."""
    sources = infos if isinstance(infos, (list, tuple)) else [infos]
    if not sources:
        raise ValueError("no training infos given")
    datasets = [OccDataset(source, cfg, train=True) for source in sources]
    return datasets[0] if len(datasets) == 1 else torch.utils.data.ConcatDataset(datasets)


class EpochSampler(torch.utils.data.distributed.DistributedSampler):
    """Each epoch's shuffled order follows from (seed, epoch) alone, split over the ranks, and
    an epoch can start part-way: a resumed run trains exactly the samples the interrupted one
    had not reached, in the same order (a fresh shuffling generator would replay epoch 0's
    order from its start)."""

    def __init__(self, dataset, world: int, rank: int, seed: int):
        super().__init__(dataset, num_replicas=world, rank=rank, shuffle=True, seed=seed)
        self._skip = 0

    def start_at(self, epoch: int, consumed: int) -> None:
        """The next iteration is epoch ``epoch`` without its first ``consumed`` indices."""
        self.set_epoch(epoch)
        self._skip = consumed

    def __iter__(self):
        skip, self._skip = self._skip, 0
        return iter(list(super().__iter__())[skip:])


@dataclass
class StepValues:
    """One step's loss terms, gradient norm and applied flag (1.0 or 0.0), in that order, as
    one tensor on the training device: reading it waits for the step to finish."""
    names: tuple[str, ...]
    values: torch.Tensor

    def read(self) -> tuple[dict[str, float], bool]:
        """-> (terms with "grad_norm", applied); a host read."""
        return terms_and_applied(self.names, self.values.tolist())


def terms_and_applied(names, numbers) -> tuple[dict[str, float], bool]:
    terms = dict(zip(names, numbers))
    return terms, terms.pop("applied") > 0


class StepLog:
    """The training loop's record of its steps. Each step's values stay on the device until,
    every ``every`` steps, one stacked copy starts for the host (asynchronous into pinned
    memory on CUDA). It is read one step later, when the next step has been queued, so the
    device still has work while the host waits. Reading writes one CSV row per step, counts
    and reports skipped steps and updates the progress bar."""

    def __init__(self, trainer: "Trainer", every: int, csv_file, header, bar):
        self.trainer, self.every, self.csv_file, self.header, self.bar = \
            trainer, every, csv_file, header, bar
        self.writer = None
        self.pending: list[tuple[dict, StepValues]] = []
        self.sent = None                  # (rows, names, host tensor, CUDA event or None)
        self.window_start = time.time()
        self.first_loss = self.last_loss = None

    def add(self, row: dict, values: StepValues) -> None:
        """After each step: reads the copy sent at an earlier step, and sends a new one every
        ``every`` steps."""
        self.pending.append((row, values))
        self.receive()
        if row["step"] % self.every == 0:
            self.send()

    def flush(self) -> None:
        """Every step's row written and counted (before a checkpoint, at the end)."""
        self.receive()
        self.send()
        self.receive()

    def send(self) -> None:
        if not self.pending:
            return
        now = time.time()
        seconds = (now - self.window_start) / len(self.pending)   # the wall time per step
        self.window_start = now
        rows = [row | {"seconds": round(seconds, 3)} for row, _ in self.pending]
        names = [values.names for _, values in self.pending]
        flat = torch.cat([values.values for _, values in self.pending])
        self.pending = []
        event = None
        if flat.device.type == "cuda":
            host = torch.empty(flat.shape, dtype=flat.dtype, pin_memory=True)
            host.copy_(flat, non_blocking=True)
            event = torch.cuda.Event()
            event.record()
        else:
            host = flat
        self.sent = (rows, names, host, event)

    def receive(self) -> None:
        if self.sent is None:
            return
        rows, names, host, event = self.sent
        self.sent = None
        if event is not None:
            event.synchronize()
        numbers, trainer = host.tolist(), self.trainer     # the one host read of the window
        for row, step_names in zip(rows, names):
            step_numbers, numbers = numbers[:len(step_names)], numbers[len(step_names):]
            terms, applied = terms_and_applied(step_names, step_numbers)
            if applied:
                self.last_loss = terms["loss"]
                self.first_loss = self.last_loss if self.first_loss is None else self.first_loss
            else:
                trainer.skipped_steps += 1
                bad = [name for name, v in terms.items() if not math.isfinite(v)]
                log.warning("step %d skipped (non-finite loss or gradient); %d so far; "
                            "non-finite: %s", row["step"], trainer.skipped_steps,
                            ", ".join(bad) or "none (flagged on another rank)")
            self._write(row | {"applied": int(applied),
                               "skipped_total": trainer.skipped_steps} | terms)
        self.bar.set_postfix(loss=f"{terms.get('loss', float('nan')):.3f}",
                             skipped=trainer.skipped_steps)

    def _write(self, row: dict) -> None:
        if self.csv_file is None:
            return
        if self.writer is None:
            fields = self.header or (list(row) + [k for k in self.trainer._all_term_names()
                                                  if k not in row])
            self.writer = csv.DictWriter(self.csv_file, fieldnames=fields,
                                         extrasaction="ignore")
            if self.header is None:
                self.writer.writeheader()
        self.writer.writerow(row)
        self.csv_file.flush()


class Trainer:
    def __init__(self, cfg: ModelConfig, infos, opts: TrainOptions):
        """``infos``: one infos path/dict, or a list of them (several dataroots train together)."""
        cfg = backbone_start(cfg, opts.backbone_weights,
                             weights_elsewhere=bool(opts.init_checkpoint or opts.resume),
                             from_scratch=opts.backbone_from_scratch)
        self.cfg, self.opts = cfg, opts
        self.rank, self.world, local_rank = distributed_context()
        self.device = process_device(opts.device, local_rank)
        if self.device.type == "cuda":
            torch.cuda.set_device(self.device)  # all_gather_object's NCCL tensors go there
        seed = opts.seed + self.rank
        torch.manual_seed(seed), np.random.seed(seed), random.seed(seed)

        self.dataset = training_dataset(infos, cfg)
        self.sampler = EpochSampler(self.dataset, self.world, self.rank, opts.seed)
        self.loader = torch.utils.data.DataLoader(
            self.dataset, batch_size=opts.batch_size, sampler=self.sampler,
            num_workers=opts.workers, collate_fn=collate, drop_last=True,
            persistent_workers=opts.workers > 0,
            pin_memory=self.device.type == "cuda")  # non_blocking copies really are (pinned)
        self.steps_per_epoch = len(self.loader)
        if self.steps_per_epoch == 0:
            raise ValueError(f"{len(self.dataset)} samples cannot fill one batch of "
                             f"{opts.batch_size} per process")

        self.model = ODG(cfg)
        if opts.backbone_weights:
            report = load_backbone_weights(self.model.backbone, opts.backbone_weights)
            log.info("backbone weights %s: %s", opts.backbone_weights, report.summary())
        if opts.init_checkpoint:
            payload = read_checkpoint(opts.init_checkpoint)
            load_weights(self.model, payload["model"])
        self.model.to(self.device)
        if self.device.type == "cuda":
            channels_last_convolutions(self.model)
        if opts.checkpoint_backbone:
            checkpoint_backbone(self.model)
        # fused on every device: one kernel per parameter group, skipping a step on a device
        # flag (found_inf), and on the CPU about 3x faster than the foreach update
        self.optimizer = torch.optim.AdamW(parameter_groups(self.model, opts), lr=opts.lr,
                                           weight_decay=opts.weight_decay, fused=True)
        self.total_steps = self.steps_per_epoch * opts.epochs
        if opts.max_steps:
            self.total_steps = min(self.total_steps, opts.max_steps)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lambda s: warmup_cosine(s, self.total_steps, opts.warmup_steps))
        self.criterion = ODGCriterion(cfg, render=opts.render,
                                      render_pixels_per_camera=opts.render_pixels_per_camera,
                                      seed=seed, renderer=training_renderer(opts.renderer,
                                                                            self.device))
        self.amp_dtype = None
        if self.device.type == "cuda":
            self.amp_dtype = torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.amp_dtype == torch.float16)
        self.step = 0
        self.skipped_steps = 0
        self._resumed_rng: dict | None = None
        self.out_dir = Path(opts.out_dir)
        if opts.resume:
            self._resume()
        self.ddp = (DistributedDataParallel(self.model, device_ids=None if self.device.type ==
                                            "cpu" else [self.device])
                    if self.world > 1 else None)
        self.forward_module = self.ddp or self.model
        if opts.compile:
            # a module compiled lazily: the first step traces it (graph breaks fall back
            # to eager); the state dict, checkpoints and DDP keep the plain module
            self.forward_module = torch.compile(self.forward_module)

    # ------------------------------------------------------------------ checkpoints
    @property
    def latest_path(self) -> Path:
        return self.out_dir / "latest.pt"

    def check_room_for_checkpoints(self) -> None:
        """Refuse to start a run whose checkpoints cannot be written: otherwise it would fail at
        its first checkpoint, or after its last step on final.pt. Each file holds the weights
        and the AdamW moments, and is written as a temporary copy beside the file it replaces:
        the disk is fullest while final.pt's copy is written beside latest.pt and the old
        final.pt, so a resumed run, whose files already exist, still needs room for one more."""
        each = tensor_bytes(self.model.state_dict()) + 2 * sum(
            p.numel() * p.element_size() for p in self.model.parameters() if p.requires_grad)
        latest = self.latest_path.stat().st_size if self.latest_path.exists() else 0
        needed, free = each + max(each - latest, 0), shutil.disk_usage(self.out_dir).free
        if free < needed:
            raise OSError(errno.ENOSPC, f"no room for the checkpoints in {self.out_dir}: "
                          f"latest.pt and final.pt take about {each / 1e6:.0f} MB each, "
                          f"{needed / 1e6:.0f} MB more are needed, {free / 1e6:.0f} MB are free")

    def save(self, path: Path | None = None) -> None:
        """Collective under DDP (every rank's RNG state goes into rank 0's file)."""
        state = self._rng_state()
        rng = [state]
        if self.world > 1:
            rng = [None] * self.world
            dist.all_gather_object(rng, state)
        if self.rank != 0:
            return
        save_checkpoint(path or self.latest_path, self.model, extra={
            "optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
            "scaler": self.scaler.state_dict(), "step": self.step,
            "skipped_steps": self.skipped_steps, "total_steps": self.total_steps, "rng": rng,
            "train_options": {k: str(v) for k, v in vars(self.opts).items()}})

    def _rng_state(self) -> dict:
        state = {"torch": torch.get_rng_state(), "criterion": self.criterion.generator.get_state()}
        if self.device.type == "cuda":
            state["cuda"] = torch.cuda.get_rng_state(self.device)
        return state

    def _set_rng_state(self, state: dict) -> None:
        torch.set_rng_state(state["torch"])
        self.criterion.generator.set_state(state["criterion"])
        if "cuda" in state and self.device.type == "cuda":
            torch.cuda.set_rng_state(state["cuda"], self.device)

    def _fetched_indices(self) -> list[int]:
        """This rank's sample indices of steps 1..self.step, in the order its loader fetched
        them (whole epochs, drop_last, then the current epoch's start)."""
        sampler = EpochSampler(self.dataset, self.world, self.rank, self.opts.seed)
        epochs, done = divmod(self.step, self.steps_per_epoch)
        fetched = []
        for epoch in range(epochs + 1):
            count = (self.steps_per_epoch if epoch < epochs else done) * self.opts.batch_size
            if count:
                sampler.set_epoch(epoch)
                fetched += list(sampler)[:count]
        return fetched

    def _resume(self) -> None:
        if not self.latest_path.exists():
            raise FileNotFoundError(f"--resume: no checkpoint at {self.latest_path}")
        payload = torch.load(self.latest_path, map_location="cpu", weights_only=False)
        self.model.load_state_dict(payload["model"])
        self.optimizer.load_state_dict(payload["optimizer"])
        self.scheduler.load_state_dict(payload["scheduler"])
        self.scaler.load_state_dict(payload["scaler"])
        self.step = payload["step"]
        self.skipped_steps = payload.get("skipped_steps", 0)
        rng = payload.get("rng")
        if rng is not None and len(rng) == self.world:
            self._resumed_rng = rng[self.rank]
        else:
            log.warning("--resume: %s holds no random-number state for %d processes; from step "
                        "%d on, dropout, render pixels and history intervals differ from a run "
                        "never stopped", self.latest_path, self.world, self.step + 1)
        # Exact only with the stopped run's 0 or 1 workers: more are dealt other batches than
        # before the stop, and 0 and 1 draw the history intervals in different processes.
        stopped_with = payload.get("train_options", {}).get("workers", "?")
        exact = self.opts.workers <= 1 and stopped_with in ("?", str(self.opts.workers))
        if self._resumed_rng is not None and not exact:
            log.warning("--resume with %d loader workers, the stopped run had %s: the history "
                        "intervals differ from a run never stopped (the same 0 or 1 workers "
                        "resume exactly)", self.opts.workers, stopped_with)
        log.info("resumed from %s at step %d", self.latest_path, self.step)

    # ------------------------------------------------------------------ one step
    def train_step(self, batch: dict) -> StepValues:
        """One step, queued on the device without waiting for it (the criterion's checks
        aside) -> its loss terms, gradient norm and applied flag, still on the device. A step
        whose loss or gradient is not finite is skipped on the device."""
        with training_phase("data"):
            batch = self._load_batch(batch)
        self.optimizer.zero_grad(set_to_none=True)
        (self.ddp or self.model).train()
        # BatchNorm statistics change in the forward pass already; a skipped step must leave
        # them as they were (a NaN batch would otherwise poison every later inference).
        buffers = {name: b.detach().clone() for name, b in self._training_statistics()}
        with training_phase("forward"):
            output = self._forward(batch)
        try:
            with training_phase("losses"):
                losses, loss = self._losses(output, batch)
            finite = torch.isfinite(loss.detach())
        except FloatingPointError as err:
            log.warning("step %d: %s", self.step + 1, err)
            # Still a backward pass: under DDP every rank's backward takes part in the
            # gradient all-reduce. The flag skips the update on every rank.
            loss = zero_weight_anchor(output)
            losses = {"loss": torch.full((), math.nan, device=loss.device)}
            finite = torch.zeros((), dtype=torch.bool, device=loss.device)
        with training_phase("backward"):
            self._backward(loss)
        with training_phase("optimizer"):
            return self._optimizer_step(losses, finite, buffers)

    def _training_statistics(self):
        """(name, buffer) of the BatchNorm layers that update their statistics in this step:
        none when BatchNorm is frozen (norm_eval), so nothing is copied for a rollback."""
        for name, module in self.model.named_modules():
            if (isinstance(module, torch.nn.modules.batchnorm._BatchNorm) and module.training
                    and module.track_running_stats):
                for buffer_name, buffer in module.named_buffers(recurse=False):
                    yield f"{name}.{buffer_name}", buffer

    def _load_batch(self, batch: dict) -> dict:
        # fit's batches come uploaded (DevicePrefetcher), for which to_device does nothing
        batch = to_device(batch, self.device)
        if self.opts.augment:
            batch = augment_batch(batch, self.cfg.pc_range)
        return batch

    def _forward(self, batch: dict):
        with torch.autocast(self.device.type, dtype=self.amp_dtype,
                            enabled=self.amp_dtype is not None):
            return self.forward_module(batch["images"], batch["ego2img"], batch["ego_warp"],
                                       batch["time_delta"], history_grad=self.opts.history_grad)

    def _losses(self, output, batch: dict):
        losses = self.criterion(output, batch)
        return losses, losses["loss"] + zero_weight_anchor(output)

    def _backward(self, loss: torch.Tensor) -> None:
        self.scaler.scale(loss).backward()

    def _optimizer_step(self, losses: dict, finite: torch.Tensor, buffers: dict) -> StepValues:
        """Clip, then update unless the loss or the gradient is not finite, decided on the
        device: no value comes to the host here."""
        self.scaler.unscale_(self.optimizer)      # records the scaler's own inf check (fp16)
        grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.opts.grad_clip,
                                                   error_if_nonfinite=False)
        applied = (finite & torch.isfinite(grad_norm)).float()
        if self.world > 1:
            dist.all_reduce(applied, op=dist.ReduceOp.MIN)   # every rank skips together
        # torch's fused AdamW leaves weights, moments and step counts alone where found_inf
        # is 1 (GradScaler's protocol; the non-fused updates refuse the flag, never ignore it)
        self.optimizer.found_inf = 1.0 - applied
        try:
            self.optimizer.step()
        finally:
            del self.optimizer.found_inf
        self.scaler.update()
        self._restore_buffers_unless(applied.bool(), buffers)
        values = [v.detach().float() for v in losses.values()] + [grad_norm.float(), applied]
        return StepValues((*losses, "grad_norm", "applied"), torch.stack(values))

    @torch.no_grad()
    def _restore_buffers_unless(self, applied: torch.Tensor, saved: dict) -> None:
        own = dict(self.model.named_buffers())
        for name, value in saved.items():
            own[name].copy_(torch.where(applied, own[name], value))

    # ------------------------------------------------------------------ loop
    def fit(self) -> dict:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        if self.rank == 0:
            self.check_room_for_checkpoints()
        log_path = self.out_dir / "train_log.csv"
        header = self._trim_log(log_path, self.step) if self.rank == 0 else None
        log_file = open(log_path, "a", newline="") if self.rank == 0 else None
        bar = tqdm(total=self.total_steps, initial=self.step, desc="train",
                   disable=not self.opts.progress or self.rank != 0)
        steps = StepLog(self, self.opts.log_every, log_file, header, bar)
        start = time.time()
        epoch, steps_done_in_epoch = divmod(self.step, self.steps_per_epoch)
        self.sampler.start_at(epoch, steps_done_in_epoch * self.opts.batch_size)
        rng, self._resumed_rng = self._resumed_rng, None
        if rng is not None and self.opts.workers == 1:
            self.loader.worker_init_fn = functools.partial(
                _replay_in_worker, self._fetched_indices())
        if rng is not None and self.opts.workers == 0 and steps_done_in_epoch == 0:
            # The stopped run would have drawn the next epoch's loader seed from this state.
            self._set_rng_state(rng)
            rng = None
        try:
            while self.step < self.total_steps:
                batches = iter(self.loader)
                if rng is not None:
                    # Making the iterator drew a loader seed, which the stopped run had drawn
                    # before this state: at its first epoch (workers) or this epoch's start.
                    self._set_rng_state(rng)
                    rng = None
                for batch in DevicePrefetcher(batches, self.device):
                    if self.step >= self.total_steps:
                        break
                    lr = self.optimizer.param_groups[1]["lr"]
                    values = self.train_step(batch)
                    self.scheduler.step()             # skipped or not (see the module's doc)
                    self.step += 1
                    steps.add({"step": self.step, "epoch": epoch, "applied": None,
                               "skipped_total": None, "lr": lr, "seconds": None,
                               "samples": " ".join(batch["token"])}, values)
                    bar.update(1)
                    if self.step % self.opts.checkpoint_every == 0:
                        steps.flush()                 # the checkpoint's skip count is exact
                        self.save()
                epoch += 1
                self.sampler.set_epoch(epoch)
            steps.flush()
        finally:
            try:
                steps.flush()                         # the rows of the steps done, if stopped
            except Exception as error:
                log.warning("the log rows of the last steps are lost: %s", error)
            bar.close()
            if log_file is not None:
                log_file.close()
        self.save()
        self.save(self.out_dir / "final.pt")
        return {"steps": self.step, "skipped_steps": self.skipped_steps,
                "first_loss": steps.first_loss, "last_loss": steps.last_loss,
                "seconds": round(time.time() - start, 1), "world_size": self.world,
                "device": str(self.device)}

    @staticmethod
    def _trim_log(path: Path, step: int) -> list[str] | None:
        """The header of the log this run appends to (None when there is none yet): new rows
        must follow the columns already there, whichever version of this code wrote them. A
        run stopped between checkpoints logged steps its checkpoint does not hold; the resumed
        run trains them again, so their old rows go (one row per step in the log), and so does
        a row cut short by the stop."""
        if not path.exists():
            return None
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
        if not rows:
            return None
        column = rows[0].index("step")
        kept = [rows[0]] + [r for r in rows[1:] if len(r) == len(rows[0])
                            and r[column].isdigit() and int(r[column]) <= step]
        if len(kept) < len(rows):
            tmp = path.with_suffix(".csv.tmp")
            with open(tmp, "w", newline="") as f:
                csv.writer(f).writerows(kept)
            os.replace(tmp, path)
        return rows[0]

    def _all_term_names(self) -> list[str]:
        names = ["loss", "grad_norm", "occ_chamfer_l0"]
        for layer in range(1, self.cfg.num_layers + 1):
            names += [f"occ_chamfer_l{layer}", f"occ_focal_l{layer}", f"box_l1_l{layer}",
                      f"box_focal_l{layer}", f"render_depth_l{layer}", f"render_sem_l{layer}"]
        return names


def _replay_in_worker(indices: list[int], worker_id: int) -> None:
    info = torch.utils.data.get_worker_info()
    replay_history_draws(info.dataset, indices)
