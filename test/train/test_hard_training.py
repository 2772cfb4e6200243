"""Hard cases of training: a few steps under torch.autograd.detect_anomaly on the tiny preset,
and steps whose loss or gradient is non-finite -- from NaN weights (a diverged network), from
a NaN pose in the batch, from an infinite time delta -- are skipped (no optimizer update),
counted and logged, and training goes on.

Already covered by test_train.py::test_nonfinite_step_is_skipped_counted_and_not_applied
(a loss poisoned after the criterion); here the non-finite values come from the network and
the data, where they actually arise.
"""
import csv
import logging
import math

import pytest
import torch

from odg_ros.train.trainer import Trainer, TrainOptions

from testing.helpers import tiny_config, write_tiny_split


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_tiny_split(tmp_path_factory.mktemp("hard_split"), 2)


def make_trainer(split, out, **kw):
    values = dict(out_dir=out, epochs=1, workers=0, warmup_steps=1, progress=False,
                  render_pixels_per_camera=32, lr=1e-3)
    values.update(kw)
    return Trainer(tiny_config(num_frames=2, image_size=(32, 88)), split, TrainOptions(**values))


def snapshot(model):
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def unchanged(model, before):
    return all(torch.allclose(v, before[k], equal_nan=True, rtol=0, atol=0)
               for k, v in model.state_dict().items())


@pytest.mark.filterwarnings("ignore:Anomaly Detection has been enabled")
def test_steps_under_detect_anomaly(split, tmp_path):
    """detect_anomaly raises inside backward at the first op that makes a NaN: none may."""
    trainer = make_trainer(split, tmp_path)
    batches = list(trainer.loader)
    with torch.autograd.detect_anomaly(check_nan=True):
        for step in range(2):
            terms, applied = trainer.train_step(batches[step % len(batches)]).read()
            assert applied, terms
            assert all(math.isfinite(v) for v in terms.values()), terms
    assert trainer.skipped_steps == 0


def test_nan_weights_are_skipped_counted_and_logged(split, tmp_path, caplog):
    trainer = make_trainer(split, tmp_path, epochs=1)
    with torch.no_grad():
        trainer.model.decoder.layers[0].points.reg[-1].bias.fill_(math.nan)   # NaN means
    before = snapshot(trainer.model)
    with caplog.at_level(logging.WARNING, logger="odg_ros.train.trainer"):
        summary = trainer.fit()
    assert summary["steps"] == 2 and summary["skipped_steps"] == 2
    assert unchanged(trainer.model, before)                       # no update was applied
    assert "non-finite loss terms: occ_chamfer_l1" in caplog.text
    assert caplog.text.count("skipped (non-finite loss or gradient)") == 2
    with open(tmp_path / "train_log.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["applied"]) for r in rows] == [0, 0]
    assert [int(r["skipped_total"]) for r in rows] == [1, 2]


def test_corrupt_geometry_in_a_batch_is_skipped_then_training_goes_on(split, tmp_path):
    """A corrupt pose cannot come from OccDataset (it checks is_rigid) but can from a custom
    loader: the frame reads zeros, its gradient is NaN, the step is skipped; the next clean
    batch trains normally."""
    trainer = make_trainer(split, tmp_path)
    clean = next(iter(trainer.loader))
    for corruption in ("nan ego_warp", "inf time_delta", "nan ego2img"):
        bad = dict(clean)
        if corruption == "nan ego_warp":
            bad["ego_warp"] = clean["ego_warp"].clone()
            bad["ego_warp"][:, 1] = math.nan
        elif corruption == "inf time_delta":
            bad["time_delta"] = clean["time_delta"].clone()
            bad["time_delta"][:, 1] = math.inf
        else:
            bad["ego2img"] = clean["ego2img"].clone()
            bad["ego2img"][:, 1, 0] = math.nan
        before = snapshot(trainer.model)
        terms, applied = trainer.train_step(bad).read()
        assert not applied and unchanged(trainer.model, before), corruption
    terms, applied = trainer.train_step(clean).read()
    assert applied and math.isfinite(terms["loss"]) and math.isfinite(terms["grad_norm"])
