"""Voxel mIoU / geometry IoU (odg_ros/metrics/miou.py): hand-computed cases and a float64
per-class counting reference on random labels."""
import numpy as np
import pytest

from odg_ros.metrics.miou import MIoU

FREE = 17


def empty(shape=(6, 5, 4)):
    return np.full(shape, FREE, dtype=np.uint8)


def test_single_voxel_perfect():
    gt = empty()
    gt[2, 3, 1] = 4
    m = MIoU()
    m.add(gt.copy(), gt)
    iou = m.per_class_iou()
    assert iou[4] == 1.0
    assert np.isnan(np.delete(iou, 4)).all()  # every other class absent from the GT
    assert m.miou() == 1.0 and m.geometry_iou() == 1.0
    assert m.result()["samples"] == 1


def test_block_shifted_by_one_voxel():
    # 4x4x4 car block, prediction shifted one voxel along x: |A & B| = 48, |A | B| = 80.
    gt, pred = empty((10, 10, 8)), empty((10, 10, 8))
    gt[2:6, 2:6, 2:6] = 4
    pred[3:7, 2:6, 2:6] = 4
    m = MIoU()
    m.add(pred, gt)
    assert m.per_class_iou()[4] == pytest.approx(48 / 80)
    assert m.miou() == pytest.approx(0.6)
    assert m.geometry_iou() == pytest.approx(0.6)


def test_wrong_class_right_geometry():
    gt, pred = empty(), empty()
    gt[1:3, 1:3, 1] = 4       # 4 car voxels
    pred[1:3, 1:3, 1] = 10    # predicted as truck
    m = MIoU()
    m.add(pred, gt)
    assert m.per_class_iou()[4] == 0.0
    assert np.isnan(m.per_class_iou()[10])  # truck never in the GT: NaN (OPUS convention)
    assert m.miou() == 0.0
    assert m.geometry_iou() == 1.0


def test_class_absent_from_gt_is_nan_and_excluded():
    gt, pred = empty(), empty()
    gt[0, 0, 0] = 4
    gt[1, 1, 1] = 10
    pred[0, 0, 0] = 4          # car right (IoU 1)
    pred[1, 1, 1] = 17         # truck missed (IoU 0)
    pred[3, 3, 3] = 3          # a bus where the GT is free: bus absent from GT -> NaN
    m = MIoU()
    m.add(pred, gt)
    iou = m.per_class_iou()
    assert iou[4] == 1.0 and iou[10] == 0.0 and np.isnan(iou[3])
    assert m.miou() == pytest.approx(0.5)        # mean of car and truck only
    # geometry: occupied GT {a, b}, predicted {a, c}: 1 / 3
    assert m.geometry_iou() == pytest.approx(1 / 3)
    assert m.result()["convention"] == "sparseocc"


def test_occ3d_convention_counts_a_predicted_class_absent_from_gt_as_zero():
    # Occ3D's Metric_mIoU: diag / (row + column - diag), NaN only where both are empty
    gt, pred = empty(), empty()
    gt[0, 0, 0] = 4
    gt[1, 1, 1] = 10
    pred[0, 0, 0] = 4
    pred[1, 1, 1] = 17
    pred[3, 3, 3] = 3          # bus: predicted, absent from GT -> 0 here
    m = MIoU(convention="occ3d")
    m.add(pred, gt)
    iou = m.per_class_iou()
    assert iou[4] == 1.0 and iou[10] == 0.0 and iou[3] == 0.0
    assert np.isnan(iou[[0, 1, 2, 5, 6, 7, 8, 9, 11, 12, 13, 14, 15, 16]]).all()
    assert m.miou() == pytest.approx(1 / 3)      # car, truck and the bus
    assert m.geometry_iou() == pytest.approx(1 / 3)
    assert m.result()["convention"] == "occ3d"
    with pytest.raises(ValueError, match="unknown mIoU convention 'occ'"):
        MIoU(convention="occ")


def test_all_free_prediction():
    gt = empty()
    gt[:, :, 0] = 11
    gt[0, 0, 1] = 4
    m = MIoU()
    m.add(empty(), gt)
    iou = m.per_class_iou()
    assert iou[11] == 0.0 and iou[4] == 0.0
    assert m.miou() == 0.0 and m.geometry_iou() == 0.0


def test_camera_mask_excludes_voxels():
    gt, pred = empty(), empty()
    gt[0, 0, 0] = 4
    gt[5, 4, 3] = 4
    pred[0, 0, 0] = 4          # only the first car voxel is predicted
    mask = np.zeros(gt.shape, dtype=bool)
    mask[0, 0, 0] = True       # the missed one is not visible in the cameras
    m = MIoU()
    m.add(pred, gt, mask)
    assert m.per_class_iou()[4] == 1.0
    m2 = MIoU()
    m2.add(pred, gt, None)
    assert m2.per_class_iou()[4] == 0.5


def test_accumulated_over_the_split_not_averaged_per_sample():
    # sample 1: car 1 of 1 right; sample 2: car 0 of 3 right -> split IoU 1/4 (not mean 0.5).
    gt1, pred1 = empty(), empty()
    gt1[0, 0, 0] = 4
    pred1[0, 0, 0] = 4
    gt2, pred2 = empty(), empty()
    gt2[1:4, 0, 0] = 4
    m = MIoU()
    m.add(pred1, gt1)
    m.add(pred2, gt2)
    assert m.per_class_iou()[4] == pytest.approx(1 / 4)
    assert m.samples == 2


def reference_iou(preds, gts, masks, num_classes):
    """Float64 per-class set counting over the split, written independently of the confusion."""
    inter = np.zeros(num_classes)
    union = np.zeros(num_classes)
    in_gt = np.zeros(num_classes)
    for pred, gt, mask in zip(preds, gts, masks):
        p, g = pred[mask], gt[mask]
        for c in range(num_classes):
            inter[c] += np.sum((p == c) & (g == c))
            union[c] += np.sum((p == c) | (g == c))
            in_gt[c] += np.sum(g == c)
    iou = np.where(in_gt > 0, inter / np.maximum(union, 1), np.nan)
    occ_p = [p[m] < num_classes for p, m in zip(preds, masks)]
    occ_g = [g[m] < num_classes for g, m in zip(gts, masks)]
    geo = (sum(np.sum(a & b) for a, b in zip(occ_p, occ_g))
           / sum(np.sum(a | b) for a, b in zip(occ_p, occ_g)))
    return iou, geo


@pytest.mark.parametrize("num_classes", [17, 15])
def test_random_labels_match_reference(num_classes):
    rng = np.random.default_rng(num_classes)
    shape = (20, 18, 6)
    preds, gts, masks = [], [], []
    m = MIoU(num_classes)
    for _ in range(3):
        # free-heavy labels; class 5 never appears in the GT, class 6 nowhere at all
        gt = rng.choice([c for c in range(num_classes + 1) if c not in (5, 6)], size=shape,
                        p=None).astype(np.uint8)
        gt[rng.random(shape) < 0.6] = num_classes
        pred = np.where(rng.random(shape) < 0.7, gt,
                        rng.integers(0, num_classes + 1, shape)).astype(np.uint8)
        pred[pred == 6] = num_classes
        mask = rng.random(shape) < 0.8
        m.add(pred, gt, mask)
        preds.append(pred), gts.append(gt), masks.append(mask)
    iou, geo = reference_iou(preds, gts, masks, num_classes)
    np.testing.assert_allclose(m.per_class_iou(), iou, rtol=1e-12, equal_nan=True)
    assert np.isnan(m.per_class_iou()[5]) and np.isnan(m.per_class_iou()[6])
    assert m.miou() == pytest.approx(np.nanmean(iou), rel=1e-12)
    assert m.geometry_iou() == pytest.approx(geo, rel=1e-12)


def test_waymo_label_set():
    gt = np.full((4, 4, 2), 15, dtype=np.uint8)
    gt[0, 0, 0] = 14
    m = MIoU(num_classes=15)
    m.add(gt.copy(), gt)
    assert m.per_class_iou().shape == (15,)
    assert m.miou() == 1.0
    with pytest.raises(ValueError, match="outside 0..15"):
        m.add(np.full_like(gt, 17), gt)


def test_nothing_added_is_nan_not_an_error():
    m = MIoU()
    assert np.isnan(m.miou()) and np.isnan(m.geometry_iou())


def test_bad_input_is_a_clear_error():
    m = MIoU()
    gt = empty()
    with pytest.raises(ValueError, match="outside 0..17"):
        m.add(np.full(gt.shape, 255, dtype=np.uint8), gt)
    with pytest.raises(ValueError, match="shape"):
        m.add(empty((6, 5, 3)), gt)
    with pytest.raises(ValueError, match="integers"):
        m.add(gt.astype(np.float32), gt)
    with pytest.raises(ValueError, match="mask shape"):
        m.add(gt, gt, np.ones((2, 2, 2), dtype=bool))
    assert m.samples == 0 and m.confusion.sum() == 0  # nothing half-added
