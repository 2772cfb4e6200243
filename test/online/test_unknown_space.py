"""Unknown space in the output field values: the grid's observed mask, the BEV's -1 and the
cloud's observed byte (online/packing.py)."""
import numpy as np

from odg_ros.classes import FREE_LABEL, OCC_CLASSES
from odg_ros.bev import bev_fields
from odg_ros.online.packing import CLOUD_DTYPE, cloud_fields, voxel_grid_fields

RANGE = (-40.0, -40.0, -1.0, 40.0, 40.0, 5.4)
ROAD = OCC_CLASSES.index("driveable_surface")
CAR = OCC_CLASSES.index("car")


def scene():
    """A road layer (z index 2), a car at x 100..104 on it; the cameras see everything
    in front of x = 110 down to the road, nothing under the road, nothing beyond x = 110."""
    grid = np.full((200, 200, 16), FREE_LABEL, np.uint8)
    grid[:, :, 2] = ROAD
    grid[100:105, 95:100, 3:7] = CAR
    observed = np.zeros(grid.shape, bool)
    observed[:110, :, 2:] = True
    return grid, observed


def test_the_grid_carries_observed_as_one_byte_a_voxel():
    grid, observed = scene()
    fields = voxel_grid_fields(grid, None, RANGE, 0.4, observed=observed)
    assert fields["observed"].dtype == np.uint8 and fields["observed"].size == grid.size
    assert np.array_equal(fields["observed"].reshape(grid.shape), observed.astype(np.uint8))
    assert voxel_grid_fields(grid, None, RANGE, 0.4)["observed"].size == 0


def test_the_bev_says_unknown_where_no_camera_sees_and_never_free():
    grid, observed = scene()
    data = np.frombuffer(bev_fields(grid, RANGE, 0.4, -1.0, 2.0, observed=observed)["data"],
                         np.int8).reshape(200, 200)                          # [y, x]
    assert data[97, 102] == 100                            # the car
    assert (data[:, :100] == 0).all()                      # seen from the road up: free
    assert (data[:, 110:] == -1).all()                     # not seen: unknown, not free
    hidden = observed.copy()
    hidden[40, 40, 4] = False                              # one voxel above the road unseen
    data = np.frombuffer(bev_fields(grid, RANGE, 0.4, -1.0, 2.0, observed=hidden)["data"],
                         np.int8).reshape(200, 200)
    assert data[40, 40] == -1
    hidden[100:105, 95:100, :] = False                     # an obstacle stays an obstacle
    data = np.frombuffer(bev_fields(grid, RANGE, 0.4, -1.0, 2.0, observed=hidden)["data"],
                         np.int8).reshape(200, 200)
    assert data[97, 102] == 100
    no_road = grid.copy()
    no_road[0, 0, 2] = FREE_LABEL                          # nothing drivable: the band counts
    data = np.frombuffer(bev_fields(no_road, RANGE, 0.4, -1.0, 2.0, observed=observed)["data"],
                         np.int8).reshape(200, 200)
    assert data[0, 0] == -1                                # (under the road is never seen)
    every = np.frombuffer(bev_fields(grid, RANGE, 0.4, -1.0, 2.0)["data"], np.int8)
    assert set(np.unique(every)) == {0, 100}               # without visibility: as before


def test_the_cloud_can_carry_observed():
    grid, observed = scene()
    fields = cloud_fields(grid, RANGE, 0.4, observed=observed)
    assert [f[0] for f in fields["fields"]] == ["x", "y", "z", "label", "observed"]
    points = np.frombuffer(fields["data"], CLOUD_DTYPE)
    flags = np.frombuffer(fields["data"], np.uint8).reshape(-1, 16)[:, 13]
    assert set(np.unique(flags)) == {0, 1}
    assert np.array_equal(flags == 1, points["x"] < 110 * 0.4 - 40)
    assert [f[0] for f in cloud_fields(grid, RANGE, 0.4)["fields"]] == ["x", "y", "z", "label"]

