"""The calibration (network/calibration.py, train/calibrate.py): confidence and box scores as
probabilities, the missed-occupancy hazard; checked by hand on small grids, the fits recover
known parameters, the grid's labels never change, and the step applies it with no host
read."""
import math

import numpy as np
import pytest
import torch

from odg_ros.model_config import load_preset
from odg_ros.network.calibration import (ABOVE_HIGH, ABOVE_LOW, HAZARD_FLOOR, HAZARD_RATES,
                                         INSIDE, OCCUPIED, UNDER, Calibration,
                                         column_features, hazard_indicators, rate_lengths)
from odg_ros.train.calibrate import fit_hazard, fit_logistic

C = 17
FREE = 17
SHAPE = (200, 200, 16)


def calibration_values(**changes):
    values = {"label_scale": [1.0 + 0.1 * c for c in range(C)],
              "label_bias": [-0.5 + 0.05 * c for c in range(C)],
              "free_scale": 0.7, "free_bias": -0.3, "box": [1.5, -0.2]}
    values.update({name: [0.0] * n for name, n in rate_lengths(C).items()})
    values.update(changes)
    return values


def config(**changes):
    return load_preset("odg_cpu", calibration=calibration_values(**changes))


def scene():
    """A road everywhere (z = 2), a car at (50..52, 60, 3..5) and a roof over nothing at
    (100, 100, 10)."""
    labels = np.full(SHAPE, FREE, np.uint8)
    labels[:, :, 2] = 11
    labels[50:53, 60, 3:6] = 4
    labels[100, 100, 10] = 15
    return labels


def test_zones_in_a_column():
    present, near, ring, zone = column_features(torch.from_numpy(scene().reshape(-1)), SHAPE,
                                                C)
    zone = zone.numpy()
    assert (zone[50, 60, :2] == UNDER).all() and (zone[50, 60, 2:6] == OCCUPIED).all()
    assert (zone[50, 60, 6:10] == ABOVE_LOW).all() and (zone[50, 60, 10:] == ABOVE_HIGH).all()
    assert (zone[100, 100, 3:10] == INSIDE).all()            # between the road and the roof
    assert (zone[0, 0, 3:7] == ABOVE_LOW).all() and (zone[0, 0, :2] == UNDER).all()
    present, near, ring = present.numpy(), near.numpy(), ring.numpy()
    assert present[4, 50, 60] and present[11, 50, 60] and present[FREE, 50, 60]
    assert not present[4, 50, 62] and near[4, 50, 61] and not near[4, 50, 62]
    assert near[4, 49, 59] and not near[4, 48, 60]
    assert ring[4, 50, 62] and ring[4, 48, 58] and not ring[4, 50, 61] and not ring[4, 50, 63]


def test_hazard_and_confidence_by_hand():
    rates = {name: [0.0] * n for name, n in rate_lengths(C).items()}
    rates["hazard_above_low"][FREE] = 0.001
    rates["hazard_above_high"][FREE] = 0.002
    rates["hazard_above_low"][4] = 0.05
    rates["hazard_inside"][15] = 0.3
    rates["hazard_near_body"][4] = 0.02
    rates["hazard_near_other"][4] = 0.01
    rates["hazard_ring_body"][4] = 0.04
    cfg = config(**rates)
    calibration = Calibration(cfg)
    labels = scene()
    raw = np.where(labels != FREE, 200, 0).astype(np.uint8)
    confidence, hazard = calibration(torch.from_numpy(labels.reshape(-1)),
                                     torch.from_numpy(raw.reshape(-1)))
    hazard = hazard.numpy().reshape(SHAPE)
    confidence = confidence.numpy().reshape(SHAPE)
    # layer 6 (1.6 m): body height, up to 1.6 m above the car (its top is layer 5)
    assert hazard[51, 60, 6] == pytest.approx(0.001 + 0.05 + 0.02)
    assert hazard[51, 60, 8] == pytest.approx(0.001 + 0.05 + 0.01)   # above the body
    assert hazard[51, 60, 11] == pytest.approx(0.002 + 0.01)         # higher still
    assert hazard[51, 61, 6] == pytest.approx(0.001 + 0.02)          # next to it
    assert hazard[51, 62, 6] == pytest.approx(0.001 + 0.04)          # in the ring
    assert hazard[51, 62, 8] == pytest.approx(0.002)     # the ring: at body height only
    assert hazard[10, 10, 5] == pytest.approx(0.001)                 # open road
    assert hazard[100, 100, 5] == pytest.approx(0.3)                 # under the roof
    assert hazard[100, 100, 12] == pytest.approx(0.001)              # above it
    assert hazard[51, 60, 0] == 0 and hazard[51, 60, 4] == 0         # under the road, the car
    # occupied: per class, sigmoid(scale logit(score) + bias)
    score = 200 / 255
    for label, (x, y, z) in ((4, (51, 60, 4)), (11, (10, 10, 2)), (15, (100, 100, 10))):
        scale, bias = 1.0 + 0.1 * label, -0.5 + 0.05 * label
        expected = 1 / (1 + math.exp(-(scale * math.log(score / (1 - score)) + bias)))
        assert confidence[x, y, z] == round(255 * expected)
    # free: 1 - sigmoid(free_scale log(hazard + floor) + free_bias)
    for at in ((51, 60, 8), (10, 10, 8), (51, 60, 0)):
        p = 1 / (1 + math.exp(-(0.7 * math.log(hazard[at] + HAZARD_FLOOR) - 0.3)))
        assert confidence[at] == round(255 * (1 - p))


def test_the_step_hazard_is_the_sum_of_the_rates_the_fit_sees():
    """train/calibrate.py fits one rate per indicator (hazard_indicators); the step's hazard
    is exactly their weighted sum."""
    from testing.helpers import driving_scene
    labels = torch.from_numpy(driving_scene(np.random.default_rng(0)).reshape(-1))
    rng = np.random.default_rng(1)
    rates = {name: (rng.random(n) * 0.1).tolist() for name, n in rate_lengths(C).items()}
    cfg = config(**rates)
    _, hazard = Calibration(cfg)(labels, torch.zeros_like(labels))
    indicators = hazard_indicators(labels, cfg)
    expected = sum((indicators[name] * torch.tensor(rates[name])[:, None, None, None]).sum(0)
                   for name in HAZARD_RATES)
    torch.testing.assert_close(hazard.view(SHAPE), expected, rtol=1e-5, atol=1e-6)
    assert (hazard > 0).float().mean() > 0.5


def test_without_a_calibration_the_confidence_is_the_raw_score():
    calibration = Calibration(load_preset("odg_cpu"))
    labels = torch.from_numpy(scene().reshape(-1))
    raw = torch.randint(0, 256, labels.shape, dtype=torch.uint8)
    confidence, hazard = calibration(labels, raw)
    assert confidence is raw and hazard is None
    score = torch.rand(10)
    assert calibration.box_score(score) is score


def test_box_scores_keep_their_order():
    calibration = Calibration(config())
    score = torch.sort(torch.rand(100), descending=True).values
    calibrated = calibration.box_score(score)
    assert (calibrated.diff() <= 0).all() and not torch.equal(calibrated, score)


@pytest.mark.parametrize("change, message", [
    (dict(label_scale=[1.0] * 3), "label_scale"),
    (dict(hazard_near_body=[-0.1] * C), "negative"),
    (dict(free_bias=float("nan")), "not finite"),
    (dict(box=[-1.0, 0.0]), "box"),
])
def test_a_calibration_that_does_not_fit_is_refused(change, message):
    with pytest.raises(ValueError, match=message):
        config(**change)


def test_fit_logistic_recovers_a_known_map():
    rng = np.random.default_rng(0)
    x = rng.normal(size=200_000)
    y = rng.random(200_000) < 1 / (1 + np.exp(-(1.7 * x - 0.4)))
    a, b = fit_logistic(x, y)
    assert a == pytest.approx(1.7, abs=0.05) and b == pytest.approx(-0.4, abs=0.05)
    # binned data (counts as weights) gives the same
    bins = np.round(x, 1)
    values = np.unique(bins)
    index = np.searchsorted(values, bins)
    right = np.bincount(index, y, minlength=len(values))
    total = np.bincount(index, minlength=len(values))
    a2, b2 = fit_logistic(np.r_[values, values], np.r_[np.ones(len(values)),
                                                       np.zeros(len(values))],
                          np.r_[right, total - right])
    assert a2 == pytest.approx(a, abs=0.05) and b2 == pytest.approx(b, abs=0.05)


def test_fit_hazard_recovers_known_rates():
    rng = np.random.default_rng(0)
    rates = np.array([0.0, 0.02, 0.3, 0.1])
    paths = rng.exponential(3.0, size=(100_000, 4)) * (rng.random((100_000, 4)) < 0.5)
    seen = rng.random(100_000) < np.exp(-paths @ rates)
    fitted = fit_hazard(paths, seen, steps=600)
    np.testing.assert_allclose(fitted, rates, atol=0.01)


def test_the_calibrated_step_changes_no_label_and_reads_nothing_back():
    """The same model with and without a calibration: the same labels, bit for bit, the
    confidence and box scores mapped; no host read inside the calibrated step."""
    from odg_ros.online.predictor import OnlinePredictor
    from testing.online import HostSyncCounter, make_model, make_sets
    model, cfg = make_model()
    above = [0.0] * (C + 1)
    above[FREE] = 0.01
    calibrated_cfg = cfg.replace(calibration=calibration_values(hazard_above_low=above,
                                                                hazard_above_high=above))
    sets = make_sets(cfg, 3)
    plain = OnlinePredictor(model, cfg, "cpu")
    calibrated = OnlinePredictor(model, calibrated_cfg, "cpu")
    for s in sets:
        a, b = plain.step(*s), calibrated.step(*s)
        np.testing.assert_array_equal(a.grid, b.grid)
        assert (a.grid != FREE).sum() > 50
        occupied = a.grid != FREE
        table = Calibration(calibrated_cfg).label_table.numpy().reshape(C + 1, 256)
        np.testing.assert_array_equal(b.confidence[occupied],
                                      table[a.grid[occupied], a.confidence[occupied]])
        assert (b.confidence[~occupied] > 200).all()                  # free: P(free) high
        # the hazard reaches the visibility: it only hides, and hides far free space
        assert not (b.observed & ~a.observed).any()
        assert b.observed.sum() < 0.9 * a.observed.sum()
        assert [x["label"] for x in a.boxes] == [x["label"] for x in b.boxes]
        expected = Calibration(calibrated_cfg).box_score(torch.tensor([x["score"]
                                                                       for x in a.boxes]))
        np.testing.assert_allclose([x["score"] for x in b.boxes], expected.numpy(), atol=1e-6)
    with torch.inference_mode(), HostSyncCounter() as counter:
        calibrated.online_step(calibrated._images, calibrated._packed)
    assert counter.ops > 1000 and counter.syncs == []


def test_the_calibration_and_the_hazard_visibility_export_to_onnx(tmp_path):
    """The calibrated part of the step (confidence, hazard, visibility with min_clear) as
    ONNX in onnxruntime equals PyTorch (the whole step's export: test_onnx_export.py)."""
    ort = pytest.importorskip("onnxruntime", reason="onnxruntime is not installed")
    pytest.importorskip("onnxscript", reason="onnxscript (torch.onnx's exporter) is missing")
    from odg_ros.online.onnx_export import _searchsorted
    from odg_ros.network.visibility import Visibility, image_bounds
    from testing.helpers import driving_scene
    from odg_ros.nuscenes_cameras import ring_ego2img
    rates = {name: [0.002] * n for name, n in rate_lengths(C).items()}
    cfg = config(**rates)

    class Part(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.calibration = Calibration(cfg)
            self.visibility = Visibility(cfg.grid_shape, cfg.pc_range, cfg.voxel_size, FREE,
                                         0.7)

        def forward(self, labels, raw, ego2img, img2ego, bounds):
            confidence, hazard = self.calibration(labels, raw)
            return confidence, hazard, self.visibility(labels, ego2img, img2ego, bounds,
                                                       hazard=hazard)

    labels = torch.from_numpy(driving_scene(np.random.default_rng(0)).reshape(-1))
    raw = torch.randint(0, 256, labels.shape, dtype=torch.uint8)
    ego2img = ring_ego2img((128, 352), 1)[0, 0]
    inputs = (labels, raw, ego2img, torch.linalg.inv(ego2img),
              torch.tensor(image_bounds([(900, 1600)] * 6, (128, 352))))
    path = tmp_path / "part.onnx"
    with torch.no_grad():
        torch.onnx.export(Part().eval(), inputs, str(path), dynamo=True, opset_version=20,
                          custom_translation_table={torch.ops.aten.searchsorted.Tensor:
                                                    _searchsorted}, verbose=False)
        expected = [t.numpy() for t in Part().eval()(*inputs)]
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, {i.name: t.numpy() for i, t in zip(session.get_inputs(), inputs)})
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_allclose(got[1], expected[1], rtol=1e-5, atol=1e-7)
    assert (got[2] != expected[2]).mean() < 1e-3 and expected[2].sum() > 10_000
