"""The same grid whatever the converter: one synthetic world (keyframe gaps 0.55 and 0.75 s)
written by `odg bag` and in the layout of each public converter (testing/bag_layouts.py), each
bag run deterministically through the node's ROS-free pipeline with its layout's documented
settings (docs/bags.md), gives the same occupancy labels on the same camera sets: at least
99.9 % of all voxels of every set, and of the voxels occupied in either grid (the few
hundred a tiny model predicts; the rest is free in both) at least 99 % where the bag carries
the same information as `odg bag`.

The Foxglove-derived layout carries the 50 Hz CAN pose on /odom (its documented setting) and
the pose at the 2 Hz keyframes on /tf (for scenes without CAN data): poses between keyframes
are then interpolated, not measured, and move some occupied voxels (93-100 % of them agree
here; with the shipped model, docs/bags.md, 99.57-99.93 % of all voxels). JPEG bytes decoded
by the node (Pillow) against the raw bgr8 images a converter decoded with OpenCV from the
same JPEGs: the same pixels at this size. Every third set is run
(the others pass as stale sets do), the same ones in every bag.
"""
from __future__ import annotations

import numpy as np
import pytest

from odg_ros.classes import FREE_LABEL
from odg_ros.online.predictor import OnlinePredictor
from testing.bag_pipeline import layout_settings, run_bag
from testing.online import make_model

AGREEMENT = 0.999           # of all voxels
OCCUPIED_AGREEMENT = 0.99   # of the voxels occupied in either grid
# poses interpolated between keyframes: what the tiny model shows (the shipped one, in
# docs/bags.md, less: 99.57-99.93 % of all voxels)
INTERPOLATED_POSES = (0.999, 0.9)
NEEDS_POSE_GAP = pytest.mark.xfail(
    reason="needs max_pose_gap: the layout's TF comes at 2 Hz keyframes only", strict=True)


@pytest.fixture(scope="module")
def model():
    return make_model()


def run(world, model, variant):
    net, cfg = model
    predictor = OnlinePredictor(net, cfg, "cpu", min_interval=0.45, visibility=False)
    bag = world.bags[variant.split()[0]]
    return run_bag(bag, predictor, layout_settings(world, variant),
                   only_us=set(world.camera_sets_us(every=3)))


@pytest.fixture(scope="module")
def reference(layout_world, model):
    result = run(layout_world, model, "odg")
    assert not result.skipped, result.skipped
    assert sorted(result.grids) == layout_world.camera_sets_us(every=3)
    return result


@pytest.mark.parametrize("variant", [
    pytest.param("foxglove", marks=NEEDS_POSE_GAP),
    pytest.param("foxglove tf", marks=NEEDS_POSE_GAP),
    "chris7462", "nuscenes2bag"])
def test_same_grid_whatever_the_converter(layout_world, model, reference, variant):
    result = run(layout_world, model, variant)
    assert not result.skipped, result.skipped           # no pose miss, no missing extrinsics
    assert sorted(result.grids) == sorted(reference.grids)
    agreement, occupied = {}, {}
    for stamp, grid in result.grids.items():
        ref = reference.grids[stamp]
        either = (grid != FREE_LABEL) | (ref != FREE_LABEL)
        agreement[stamp] = float(np.mean(grid == ref))
        occupied[stamp] = float(np.mean(grid[either] == ref[either]))
    least, least_occupied = INTERPOLATED_POSES if variant == "foxglove tf" else \
        (AGREEMENT, OCCUPIED_AGREEMENT)
    assert min(agreement.values()) >= least, agreement
    assert min(occupied.values()) >= least_occupied, occupied
