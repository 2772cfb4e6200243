"""Training: the loss goes down, resume continues exactly, non-finite steps are skipped and
counted, several infos files train together, DDP with 2 CPU processes (gloo) via torchrun."""
import csv
import errno
import gc
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
import torch.distributed as dist

from odg_ros.commands import main as cli_main
from odg_ros.commands import train as train_command
from odg_ros.data.dataset import OccDataset, replay_history_draws
from odg_ros.losses.criterion import ODGCriterion
from odg_ros.network import ODG
from odg_ros.network.checkpoint import load_model, save_checkpoint
from odg_ros.train import trainer as trainer_module
from odg_ros.bench.census import Census, CensusMode, force_cuda_paths
from odg_ros.train.schedule import warmup_cosine
from odg_ros.train.trainer import (StepLog, Trainer, TrainOptions, process_device,
                                  training_dataset, training_renderer)

from testing.helpers import tiny_config, write_tiny_split


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_tiny_split(tmp_path_factory.mktemp("split"), 2)


def options(out, **kw):
    values = dict(out_dir=out, epochs=1, workers=0, warmup_steps=1, progress=False,
                  render_pixels_per_camera=64, lr=1e-3)
    values.update(kw)
    return TrainOptions(**values)


def read_log(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_each_process_trains_on_its_own_gpu(monkeypatch):
    """Under torchrun a bare ``cuda`` (and ``auto`` on a GPU machine) is the local rank's GPU,
    never every rank on GPU 0 (``torch.cuda.set_device`` also needs the index)."""
    assert process_device("cpu", 1) == torch.device("cpu")
    assert process_device("cuda", 1) == torch.device("cuda", 1)
    assert process_device("cuda:0", 1) == torch.device("cuda", 0)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert process_device("auto", 1) == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert process_device("auto", 1) == torch.device("cuda", 1)


def test_render_loss_renderer_is_ours_or_gsplat_on_cuda():
    from odg_ros.render.gsplat_backend import render_scenes_gsplat
    assert training_renderer("torch", torch.device("cpu")) is None   # the criterion's default
    assert training_renderer("gsplat", torch.device("cuda", 0)) is render_scenes_gsplat
    with pytest.raises(ValueError, match="needs a CUDA device"):
        training_renderer("gsplat", torch.device("cpu"))
    with pytest.raises(ValueError, match="torch or gsplat"):
        training_renderer("inria", torch.device("cpu"))
    assert training_renderer("auto", torch.device("cpu")) is None


def test_auto_renderer_is_gsplat_on_cuda_only_where_installed(monkeypatch):
    from odg_ros.train import trainer as trainer_module
    monkeypatch.setattr(trainer_module.importlib.util, "find_spec", lambda name: None)
    assert training_renderer("auto", torch.device("cuda", 0)) is None


def render_loss_log(split, out, **kw):
    """The tiny run's render-loss columns, one row per step (every step applied)."""
    summary = Trainer(tiny_config(num_frames=2), split, options(out, epochs=2, **kw)).fit()
    assert summary["steps"] == 4 and summary["skipped_steps"] == 0
    rows = read_log(out / "train_log.csv")
    return np.array([[float(v) for k, v in r.items() if k.startswith("render_")] for r in rows])


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="gsplat's rasteriser has CUDA kernels only; no GPU on this machine")
def test_trains_on_cuda_with_the_gsplat_renderer(split, tmp_path):
    """The same run with our renderer and with gsplat's kernels logs the same render losses,
    step by step (float32 kernels that differ at the 1/255 skip: to 1%). The tiny world's first
    keyframe has no LiDAR pixel in view: its steps cost 0 with either renderer."""
    ours = render_loss_log(split, tmp_path / "torch", device="cuda", renderer="torch")
    theirs = render_loss_log(split, tmp_path / "gsplat", device="cuda", renderer="gsplat")
    assert (ours > 0).any(axis=1).sum() == 2 and (ours == 0).all(axis=1).sum() == 2
    np.testing.assert_allclose(theirs, ours, rtol=1e-2, atol=1e-6)


def test_schedule_warms_up_then_decays():
    assert warmup_cosine(0, 100, 10) == pytest.approx(1 / 3)
    assert warmup_cosine(10, 100, 10) == pytest.approx(1.0)
    assert warmup_cosine(55, 100, 10) == pytest.approx(0.5 * (1 + 1e-3), rel=1e-3)
    assert warmup_cosine(100, 100, 10) == pytest.approx(1e-3)


def test_loss_goes_down_on_a_tiny_split(split, tmp_path):
    cfg = tiny_config(num_frames=2)
    trainer = Trainer(cfg, split, options(tmp_path, epochs=6))
    summary = trainer.fit()
    rows = read_log(tmp_path / "train_log.csv")
    losses = [float(r["loss"]) for r in rows]
    assert summary["steps"] == len(rows) == 12 and summary["skipped_steps"] == 0
    assert sum(losses[-3:]) < 0.9 * sum(losses[:3]), losses
    assert {"occ_chamfer_l0", "occ_focal_l6", "box_l1_l6", "render_depth_l1"} <= set(rows[0])
    assert (tmp_path / "final.pt").exists()
    model, loaded_cfg = load_model(tmp_path / "final.pt")
    assert loaded_cfg == cfg


def test_resume_continues_where_it_stopped(split, tmp_path):
    cfg = tiny_config(num_frames=2)
    Trainer(cfg, split, options(tmp_path, epochs=1)).fit()
    resumed = Trainer(cfg, split, options(tmp_path, epochs=2, resume=True))
    assert resumed.step == 2
    assert resumed.optimizer.state_dict()["state"]  # Adam moments restored
    assert resumed.scheduler.last_epoch == 2
    summary = resumed.fit()
    assert summary["steps"] == 4
    assert len(read_log(tmp_path / "train_log.csv")) == 4


def test_resume_mid_epoch_trains_what_the_interrupted_run_had_not(tmp_path):
    """Stopped after 7 of 2 x 5 steps and resumed, a run trains the same samples in the same
    order as one never stopped: the rest of epoch 1, not epoch 0's order from its start."""
    five = write_tiny_split(tmp_path / "five", 5)
    cfg = tiny_config(num_frames=2)

    def trained_samples(out):
        return [r["samples"] for r in read_log(out / "train_log.csv")]

    whole = tmp_path / "whole"
    Trainer(cfg, five, options(whole, epochs=2)).fit()
    stopped = tmp_path / "stopped"
    Trainer(cfg, five, options(stopped, epochs=2, max_steps=7)).fit()
    Trainer(cfg, five, options(stopped, epochs=2, resume=True)).fit()
    order = trained_samples(whole)
    assert sorted(order[:5]) == sorted(order[5:]) and len(set(order[:5])) == 5  # each epoch: all
    assert order[:5] != order[5:]  # reshuffled (this seed; 1 in 120 orders would repeat)
    assert trained_samples(stopped) == order


def _kill_at(trainer, step):
    """``trainer.fit()`` raises KeyboardInterrupt before training step ``step + 1``."""
    real_step = trainer.train_step

    def step_until_killed(batch):
        if trainer.step == step:
            raise KeyboardInterrupt
        return real_step(batch)
    trainer.train_step = step_until_killed


def _logged_terms(out):
    return [{k: v for k, v in row.items() if k != "seconds"}
            for row in read_log(out / "train_log.csv")]


def _weights(path):
    return torch.load(path, map_location="cpu", weights_only=False)["model"]


@pytest.fixture(scope="module")
def three(tmp_path_factory):
    """One scene of 3 keyframes: from the second on, 6 earlier camera sets, so the training
    history interval is drawn from 4-6."""
    return write_tiny_split(tmp_path_factory.mktemp("three"), 3)


@pytest.fixture(scope="module")
def never_stopped(three, tmp_path_factory):
    """workers -> output folder of 2 epochs x 3 steps trained without a stop."""
    runs = {}

    def run(workers):
        if workers not in runs:
            out = tmp_path_factory.mktemp(f"whole{workers}")
            Trainer(tiny_config(num_frames=2), three,
                    options(out, epochs=2, workers=workers)).fit()
            runs[workers] = out
        return runs[workers]
    return run


@pytest.mark.parametrize("workers, killed_at, checkpoint_every", [
    (0, 5, 2),   # mid-epoch: resumes at step 4 (epoch 1, one step in)
    (0, 4, 3),   # resumes at step 3, an epoch boundary (the next loader seed is still to draw)
    (1, 5, 2),   # one loader worker: its history-interval draws are replayed
])
def test_resumed_run_is_the_run_never_stopped(three, never_stopped, tmp_path, workers,
                                              killed_at, checkpoint_every):
    """Killed and resumed, a run logs the same samples and loss terms at every step and ends
    with the same weights, to the last bit, as the run never stopped: dropout, render pixels
    and the history intervals continue from where they were. The steps after the checkpoint
    are trained again and logged once, a row cut short by the kill dropped."""
    cfg = tiny_config(num_frames=2)
    killed = tmp_path / "killed"
    interrupted = Trainer(cfg, three, options(killed, epochs=2, workers=workers,
                                              checkpoint_every=checkpoint_every))
    _kill_at(interrupted, killed_at)
    with pytest.raises(KeyboardInterrupt):
        interrupted.fit()
    assert len(read_log(killed / "train_log.csv")) == killed_at
    with open(killed / "train_log.csv", "a") as log_file:
        log_file.write("1")  # the start of a row the kill cut short
    resumed = Trainer(cfg, three, options(killed, epochs=2, workers=workers,
                                          checkpoint_every=checkpoint_every, resume=True))
    assert resumed.step == killed_at // checkpoint_every * checkpoint_every
    resumed.fit()
    whole = never_stopped(workers)
    assert [int(r["step"]) for r in read_log(killed / "train_log.csv")] == list(range(1, 7))
    assert _logged_terms(killed) == _logged_terms(whole)
    assert _same(_weights(killed / "final.pt"), _weights(whole / "final.pt"))


def test_a_checkpoint_without_random_state_still_resumes(split, tmp_path, caplog):
    """Files written before the RNG state was saved resume with a warning (not exactly)."""
    cfg = tiny_config(num_frames=2)
    Trainer(cfg, split, options(tmp_path, epochs=1)).fit()
    payload = torch.load(tmp_path / "latest.pt", weights_only=False)
    del payload["rng"]
    torch.save(payload, tmp_path / "latest.pt")
    with caplog.at_level("WARNING"):
        resumed = Trainer(cfg, split, options(tmp_path, epochs=2, resume=True))
    assert "holds no random-number state" in caplog.text
    assert resumed.fit()["steps"] == 4


def test_resuming_with_another_number_of_loader_workers_says_it_is_not_exact(split, tmp_path,
                                                                           caplog):
    cfg = tiny_config(num_frames=2)
    Trainer(cfg, split, options(tmp_path, epochs=1, workers=0)).fit()
    with caplog.at_level("WARNING"):
        Trainer(cfg, split, options(tmp_path, epochs=2, workers=0, resume=True))
    assert "loader workers" not in caplog.text
    with caplog.at_level("WARNING"):
        Trainer(cfg, split, options(tmp_path, epochs=2, workers=1, resume=True))
    assert "--resume with 1 loader workers, the stopped run had 0" in caplog.text


def test_replayed_history_draws_leave_the_rng_where_loading_the_samples_would(tmp_path):
    paths = [write_tiny_split(tmp_path / name, 5) for name in ("a", "b")]
    cfg = tiny_config(num_frames=2)
    both = training_dataset([str(p) for p in paths], cfg)
    earlier, then = [7, 1, 9, 3, 6, 8], 4
    torch.manual_seed(3)
    for index in earlier:
        both[index]
    loaded = [both.datasets[0].history_choices(then)[1] for _ in range(8)]
    torch.manual_seed(3)
    replay_history_draws(both, earlier)
    assert [both.datasets[0].history_choices(then)[1] for _ in range(8)] == loaded
    torch.manual_seed(3)
    replay_history_draws(both, earlier[1:])  # one draw fewer: a different stream (can fail)
    assert [both.datasets[0].history_choices(then)[1] for _ in range(8)] != loaded


def test_init_from_a_shipped_checkpoint_with_a_smaller_final_point_budget(split, tmp_path):
    """--init takes an int8 shipped file and a final layer with fewer points (grown)."""
    small = tiny_config(num_frames=2)
    save_checkpoint(tmp_path / "small_int8.pt", ODG(small), compress="int8")
    big = small.replace(points_per_layer=small.points_per_layer[:-1] + (16,))
    trainer = Trainer(big, split, options(tmp_path / "run", init_checkpoint=str(
        tmp_path / "small_int8.pt")))
    reference, _ = load_model(tmp_path / "small_int8.pt")
    key = "decoder.layers.5.points.cls.6.bias"
    grown = trainer.model.state_dict()[key].view(2, 8, -1)
    assert torch.allclose(grown, reference.state_dict()[key].view(1, 8, -1).expand_as(grown))
    assert trainer.fit()["skipped_steps"] == 0


def _same(a, b):
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.shape == b.shape and torch.equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def test_several_infos_files_train_together_each_from_its_own_dataroot(tmp_path):
    """Two dataroots naming their scenes alike (two odg synth runs): every sample, history
    included, must come from its own root, as if that file were loaded alone."""
    paths = []
    for name, keyframes, yaw_rate in (("a", 2, 0.0), ("b", 3, 0.3)):
        paths.append(write_tiny_split(tmp_path / name, keyframes, yaw_rate=yaw_rate))
    cfg = tiny_config(num_frames=2)
    both = training_dataset([str(p) for p in paths], cfg)
    alone = [OccDataset(str(p), cfg, train=True) for p in paths]
    assert len(both) == 5
    for index, (part, local) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1), (1, 2)]):
        torch.manual_seed(index)
        mixed = both[index]
        torch.manual_seed(index)
        assert _same(mixed, alone[part][local]), index
    torch.manual_seed(0)
    assert not _same(both[2], alone[0][0])  # the roots differ (the check above can fail)
    with pytest.raises(ValueError, match="no training infos"):
        training_dataset([], cfg)


def test_nonfinite_step_is_skipped_counted_and_not_applied(split, tmp_path, monkeypatch):
    cfg = tiny_config(num_frames=2)
    trainer = Trainer(cfg, split, options(tmp_path, epochs=1))
    real = ODGCriterion.__call__
    calls = {"n": 0}

    def poisoned(criterion, output, batch):
        calls["n"] += 1
        losses = real(criterion, output, batch)
        if calls["n"] == 1:
            losses["loss"] = losses["loss"] * float("nan")
        return losses
    monkeypatch.setattr(ODGCriterion, "__call__", poisoned)
    before = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    terms, applied = trainer.train_step(next(iter(trainer.loader))).read()
    assert not applied
    for k, v in trainer.model.state_dict().items():
        assert torch.equal(v, before[k]), k
    summary = trainer.fit()
    assert summary["skipped_steps"] == 0  # fit() counts its own steps: the poison was used
    terms, applied = trainer.train_step(next(iter(trainer.loader))).read()
    assert applied and terms["loss"] == terms["loss"]


def _optimizer_and_model_state(trainer):
    moments = [t.clone() for state in trainer.optimizer.state.values() for t in state.values()]
    return moments, {k: v.clone() for k, v in trainer.model.state_dict().items()}


def test_a_nan_step_is_skipped_on_the_device_and_reported_at_the_next_read(
        split, tmp_path, monkeypatch, caplog):
    """Step 3 of 6 has a NaN loss (so NaN gradients) and losses are read every 4 steps: its
    update leaves weights, BatchNorm statistics, AdamW moments and step counts as they were,
    the host learns of it at the read after step 4 (done when step 5 is queued), the learning
    rate schedule goes on, and the log says which values were not finite."""
    trainer = Trainer(tiny_config(num_frames=2, image_size=(32, 88)), split,
                      options(tmp_path, epochs=3, log_every=4))
    real_criterion, real_step = ODGCriterion.__call__, trainer.train_step
    skipped_known, around_step_3 = [], []

    def poisoned(criterion, output, batch):
        losses = real_criterion(criterion, output, batch)
        if trainer.step == 2:
            losses["loss"] = losses["loss"] * float("nan")
        return losses

    def watched(batch):
        skipped_known.append(trainer.skipped_steps)
        if trainer.step == 2:
            around_step_3.append(_optimizer_and_model_state(trainer))
        values = real_step(batch)
        if trainer.step == 2:
            around_step_3.append(_optimizer_and_model_state(trainer))
        return values
    monkeypatch.setattr(ODGCriterion, "__call__", poisoned)
    trainer.train_step = watched
    with caplog.at_level("WARNING", logger="odg_ros.train.trainer"):
        summary = trainer.fit()
    (moments, weights), (moments_after, weights_after) = around_step_3
    assert moments and len(moments) == len(moments_after)
    assert [i for i, (a, b) in enumerate(zip(moments, moments_after)) if not torch.equal(a, b)] \
        == []
    assert any("running_mean" in k for k in weights)       # BatchNorm trains in this model
    assert [k for k, v in weights_after.items() if not torch.equal(weights[k], v)] == []
    assert skipped_known == [0, 0, 0, 0, 0, 1]             # counted at the read, not before
    assert summary["steps"] == 6 and summary["skipped_steps"] == 1
    assert "step 3 skipped (non-finite loss or gradient); 1 so far; non-finite: loss, " \
           "grad_norm" in caplog.text
    rows = read_log(tmp_path / "train_log.csv")
    assert [int(r["applied"]) for r in rows] == [1, 1, 0, 1, 1, 1]
    assert [int(r["skipped_total"]) for r in rows] == [0, 0, 1, 1, 1, 1]
    assert rows[2]["loss"] == "nan" and float(rows[3]["loss"]) > 0
    assert [float(r["lr"]) for r in rows] == pytest.approx(
        [1e-3 * warmup_cosine(step, 6, 1) for step in range(6)])     # skipped or not
    assert trainer.optimizer.state_dict()["state"][0]["step"] == 5   # updates applied


def test_the_trainer_reads_the_device_only_at_its_log_reads(split, tmp_path, monkeypatch):
    """Four steps read every 2, the CUDA paths forced: the trainer's own code makes no host
    sync within a step, and one per read of the log (after step 2, when step 3 is queued;
    at the end)."""
    trainer = Trainer(tiny_config(num_frames=2, image_size=(32, 88)), split, options(
        tmp_path, epochs=2, log_every=2, checkpoint_every=1000, augment=False))
    force_cuda_paths(trainer)
    syncs = {"train_step": [], "add": [], "flush": []}

    def counted(function):
        def run(*args, **kwargs):
            census = Census()
            with CensusMode(census, device_type=None):
                out = function(*args, **kwargs)
            syncs[function.__name__].append(sum(n for (_, line), n in census.syncs.items()
                                                if line.startswith("train/trainer.py")))
            return out
        return run
    trainer.train_step = counted(trainer.train_step)
    monkeypatch.setattr(StepLog, "add", counted(StepLog.add))
    monkeypatch.setattr(StepLog, "flush", counted(StepLog.flush))
    assert trainer.fit()["steps"] == 4
    assert syncs == {"train_step": [0] * 4, "add": [0, 0, 1, 0], "flush": [1, 0]}


KILLED_AT_STEP_3 = """
import sys
from odg_ros.commands import main
from odg_ros.train.trainer import Trainer
real_step = Trainer.train_step


def step_until_killed(trainer, batch):
    if trainer.step == 3:
        raise SystemExit(3)
    return real_step(trainer, batch)


Trainer.train_step = step_until_killed
sys.exit(main())
"""


def test_ddp_two_cpu_processes_with_torchrun(split, tmp_path):
    """Two ranks in sync, one log and checkpoint; killed after step 3 (checkpoint at 2) and
    resumed, the run ends with the weights of the run never stopped: each rank's RNG state
    comes back to that rank."""
    env = dict(os.environ, GLOO_SOCKET_IFNAME="lo", MASTER_ADDR="127.0.0.1",
               OMP_NUM_THREADS="1")
    killer = tmp_path / "killed_at_step_3.py"
    killer.write_text(KILLED_AT_STEP_3)

    def torchrun(program, out, *extra):
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone",
               "--nproc_per_node", "2", *program, "train", "--preset", "odg_cpu",
               "--data", str(split), "--out", str(out), "--steps", "4",
               "--checkpoint-every", "2", "--log-every", "3", "--workers", "0",
               "--render-pixels", "32",
               "--device", "cpu", "--set", "backbone=resnet18", "--set", "image_size=[64,176]",
               "--set", "num_frames=2", "--set", "embed_dims=64", "--set", "fpn_channels=64",
               "--set", "num_static=20", "--set", "num_dynamic=6", "--set", "ffn_dims=128",
               "--set", "points_per_layer=[1,2,2,4,4,8]", "--set", "mixing_out_points=8",
               *extra]
        return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)

    whole = tmp_path / "whole"
    result = torchrun(["-m", "odg_ros.commands"], whole)
    assert result.returncode == 0, result.stderr[-3000:]
    assert '"world_size": 2' in result.stdout
    rows = read_log(whole / "train_log.csv")
    assert len(rows) == 4  # 2 samples over 2 ranks: 1 step per epoch; only rank 0 logs
    load_model(whole / "final.pt")  # both ranks stayed in sync: one checkpoint

    killed = tmp_path / "killed"
    assert torchrun([str(killer)], killed).returncode != 0
    assert len(read_log(killed / "train_log.csv")) == 3
    result = torchrun(["-m", "odg_ros.commands"], killed, "--resume")
    assert result.returncode == 0, result.stderr[-3000:]
    assert _logged_terms(killed) == _logged_terms(whole)
    assert _same(_weights(killed / "final.pt"), _weights(whole / "final.pt"))


def test_train_command_ends_its_process_group(split, tmp_path, monkeypatch, capsys):
    """A torchrun rank frees its gloo group before the interpreter shuts down, after a run and
    after a failure: freed by the shutdown, gloo's threads can abort a finished run (SIGABRT,
    "terminate called without an active exception"; CI saw it on rank 1 of a resumed run).
    Destroying the group is not enough: the DDP wrapper holds it too, and the Trainer sits in
    reference cycles, so no Trainer may be left when the group is destroyed."""
    def one_rank_group():
        dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)

    trainers_left = []

    def end_and_count(real=train_command.end_distributed):
        real()
        trainers_left.append(sum(type(o) is Trainer for o in gc.get_objects()))
    monkeypatch.setattr(train_command, "end_distributed", end_and_count)
    tiny = ["--preset", "odg_cpu", "--steps", "1", "--workers", "0", "--render-pixels", "16",
            "--device", "cpu", "--set", "backbone=resnet18", "--set", "image_size=[64,176]",
            "--set", "num_frames=2", "--set", "embed_dims=64", "--set", "fpn_channels=64",
            "--set", "num_static=20", "--set", "num_dynamic=6", "--set", "ffn_dims=128",
            "--set", "points_per_layer=[1,2,2,4,4,8]", "--set", "mixing_out_points=8"]
    try:
        one_rank_group()
        assert cli_main(["train", "--data", str(split), "--out", str(tmp_path / "run"),
                         *tiny]) == 0
        run = tmp_path / "run"
        assert f"odg train: wrote {run / 'final.pt'} (the trained model" in \
            capsys.readouterr().err and (run / "final.pt").is_file()
        assert not dist.is_initialized()
        one_rank_group()
        assert cli_main(["train", "--data", str(split), "--out", str(tmp_path / "failed"),
                         "--resume", *tiny]) == 2        # after the model is built
        assert "no checkpoint" in capsys.readouterr().err
        assert not dist.is_initialized()
        assert trainers_left == [0, 0]
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


def test_a_run_without_room_for_its_checkpoints_stops_before_training(split, tmp_path,
                                                                     monkeypatch):
    """The room asked for is two checkpoints of the size the run really writes (weights and
    AdamW moments); without it the run stops before its first step, saying how much."""
    done = tmp_path / "done"
    Trainer(tiny_config(num_frames=2), split, options(done, max_steps=1)).fit()
    written = (done / "final.pt").stat().st_size
    disk = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(trainer_module.shutil, "disk_usage",
                        lambda path: disk._replace(free=int(1.9 * written)))
    cut_short = tmp_path / "cut_short"
    with pytest.raises(OSError, match=r"no room for the checkpoints in .*cut_short: latest.pt "
                                      r"and final.pt take about (\d+) MB each") as raised:
        Trainer(tiny_config(num_frames=2), split, options(cut_short, max_steps=1)).fit()
    assert raised.value.errno == errno.ENOSPC
    each = int(re.search(r"about (\d+) MB each", str(raised.value)).group(1)) * 1e6
    assert abs(each - written) < 0.02 * written + 1e6
    assert not (cut_short / "train_log.csv").exists()
    # a resumed run's latest.pt counts as room, but the temporary copy of final.pt is written
    # beside it and the old final.pt: one checkpoint more
    def resume_with_free(fraction):
        monkeypatch.setattr(trainer_module.shutil, "disk_usage",
                            lambda path: disk._replace(free=int(fraction * written)))
        Trainer(tiny_config(num_frames=2), split, options(done, epochs=2, resume=True)).fit()

    with pytest.raises(OSError, match="no room for the checkpoints"):
        resume_with_free(0.9)
    resume_with_free(1.1)
