"""Message field values (bytes, layouts, conventions) and the diagnostics summary."""
import math

import numpy as np
import pytest

from odg_ros.classes import FREE_LABEL, OCC_CLASSES, WAYMO_OCC_CLASSES
from odg_ros.model_config import load_preset
from odg_ros.online import diagnostics
from odg_ros.bev import bev_fields
from odg_ros.online.packing import CLOUD_DTYPE, cloud_fields, object_fields, \
    voxel_grid_fields
from odg_ros.rotation import yaw_to_quaternion

RANGE = (-40.0, -40.0, -1.0, 40.0, 40.0, 5.4)


def sample_grid():
    grid = np.full((200, 200, 16), FREE_LABEL, np.uint8)
    grid[100, 120, 3] = OCC_CLASSES.index("car")
    grid[0, 0, 0] = OCC_CLASSES.index("driveable_surface")
    grid[199, 5, 15] = OCC_CLASSES.index("vegetation")
    grid[50, 60, 1] = OCC_CLASSES.index("sidewalk")
    return grid


def test_voxel_grid_fields_are_flat_uint8_in_xyz_c_order():
    grid = sample_grid()
    confidence = np.arange(grid.size, dtype=np.uint32).astype(np.uint8).reshape(grid.shape)
    fields = voxel_grid_fields(grid, confidence, RANGE, 0.4)
    for name in ("labels", "confidence"):
        assert fields[name].dtype == np.uint8 and fields[name].shape == (grid.size,)
    assert np.shares_memory(fields["labels"], grid)             # a view: no copy
    back = np.frombuffer(fields["labels"].tobytes(), np.uint8).reshape(200, 200, 16)
    assert np.array_equal(back, grid)
    i, j, k = 100, 120, 3
    assert fields["labels"][(i * 200 + j) * 16 + k] == OCC_CLASSES.index("car")
    assert np.array_equal(np.frombuffer(fields["confidence"], np.uint8), confidence.ravel())
    assert fields["origin_position"] == (-40.0, -40.0, -1.0)
    assert (fields["size_x"], fields["size_y"], fields["size_z"]) == (200, 200, 16)
    assert fields["class_names"][FREE_LABEL] == "free" and fields["free_label"] == 17
    assert voxel_grid_fields(grid, None, RANGE, 0.4)["confidence"].size == 0
    transposed = np.asfortranarray(grid)                     # still read in C order
    assert voxel_grid_fields(transposed, None, RANGE, 0.4)["labels"].tobytes() == grid.tobytes()
    with pytest.raises(ValueError):
        voxel_grid_fields(grid.astype(np.int32), None, RANGE, 0.4)


def test_cloud_has_one_point_per_occupied_voxel_at_its_centre():
    fields = cloud_fields(sample_grid(), RANGE, 0.4)
    assert fields["width"] == 4 and fields["point_step"] == 16
    assert fields["row_step"] == 64 and len(fields["data"]) == 64
    points = np.frombuffer(fields["data"], CLOUD_DTYPE)
    car = points[points["label"] == OCC_CLASSES.index("car")][0]
    assert (car["x"], car["y"], car["z"]) == pytest.approx((0.2, 8.2, 0.4))
    assert [f[0] for f in fields["fields"]] == ["x", "y", "z", "label"]
    empty = cloud_fields(np.full((200, 200, 16), FREE_LABEL, np.uint8), RANGE, 0.4)
    assert empty["width"] == 0 and empty["data"] == b""


def test_bev_marks_non_drivable_labels_in_the_height_band():
    grid = sample_grid()
    fields = bev_fields(grid, RANGE, 0.4, min_z=-1.0, max_z=2.0)
    data = np.frombuffer(fields["data"], np.int8).reshape(200, 200)     # [y, x]
    assert data[120, 100] == 100            # car
    assert data[60, 50] == 100              # sidewalk: not drivable
    assert data[0, 0] == 0                  # driveable surface
    assert data[5, 199] == 0                # vegetation at 5.2 m: above the band
    assert (data == 100).sum() == 2
    assert fields["width"] == 200 and fields["origin_position"] == (-40.0, -40.0, 0.0)
    high = np.frombuffer(bev_fields(grid, RANGE, 0.4, 0.5, 5.4)["data"], np.int8)
    assert high.reshape(200, 200)[5, 199] == 100 and high.reshape(200, 200)[60, 50] == 0


def test_waymo_model_messages_carry_the_waymo_label_set():
    """The node passes cfg.labels: a Waymo model's grid says free = 15 and names Waymo's
    classes; its cloud and BEV map treat 15 as free and road as drivable."""
    labels = load_preset("odg_waymo_t").labels
    grid = np.full((200, 200, 16), 15, np.uint8)
    grid[100, 120, 3] = WAYMO_OCC_CLASSES.index("vehicle")
    grid[0, 0, 0] = WAYMO_OCC_CLASSES.index("road")
    grid[50, 60, 1] = WAYMO_OCC_CLASSES.index("walkable")
    fields = voxel_grid_fields(grid, None, RANGE, 0.4, labels)
    assert fields["free_label"] == 15 and fields["class_names"] == list(WAYMO_OCC_CLASSES)
    assert cloud_fields(grid, RANGE, 0.4, labels)["width"] == 3
    data = np.frombuffer(bev_fields(grid, RANGE, 0.4, -1.0, 2.0, labels)["data"], np.int8)
    data = data.reshape(200, 200)
    assert data[120, 100] == 100 and data[60, 50] == 100 and data[0, 0] == 0
    assert (data == 100).sum() == 2


def test_object_fields_follow_the_message_conventions():
    box = {"label": 0, "class_name": "car", "score": 0.9, "center": [1.0, 2.0, 0.5],
           "size": [1.9, 4.5, 1.6], "yaw": math.pi / 2, "velocity": [3.0, -1.0]}
    fields = object_fields(box)
    assert fields["size"] == (4.5, 1.9, 1.6)               # x = length along the heading
    w, x, y, z = fields["orientation"]
    assert (w, z) == pytest.approx((math.cos(math.pi / 4), math.sin(math.pi / 4)))
    assert fields["velocity"] == (3.0, -1.0, 0.0)
    assert yaw_to_quaternion(0.0) == (1.0, 0.0, 0.0, 0.0)


def test_diagnostics_rates_latency_and_levels():
    clock = [100.0]
    stats = diagnostics.PipelineStats(window=50, stale_after_s=5.0, clock=lambda: clock[0])
    counters = {"pose_miss": 0, "stale_sets_dropped": 0}
    status = stats.status(counters)
    assert status["level"] == diagnostics.WARN and "waiting" in status["message"]
    for k in range(20):
        clock[0] += 0.1                                   # 10 Hz
        stats.record_output(image_stamp=1000.0 + 0.1 * k, now=1000.0 + 0.1 * k + 0.2,
                            timings={"model": 0.05, "upload": 0.03}, received=clock[0] - 0.09)
    snap = stats.snapshot()
    assert snap["rate_hz"] == pytest.approx(10.0)
    assert snap["stamp_age_ms"]["p50"] == pytest.approx(200.0)          # node clock
    assert snap["receipt_to_publish_ms"]["p50"] == pytest.approx(90.0)  # steady clock
    assert snap["stage_ms"]["model"] == pytest.approx(50.0)
    assert snap["stage_ms"]["publish"] is None
    assert stats.status(counters)["level"] == diagnostics.OK
    counters["stale_sets_dropped"] = 5                    # load shedding: still OK
    assert stats.status(counters)["level"] == diagnostics.OK
    counters["pose_miss"] = 2
    status = stats.status(counters)
    assert status["level"] == diagnostics.WARN and "pose_miss: 2" in status["message"]
    assert ("pose_miss", "2") in status["values"]
    assert stats.status(counters)["level"] == diagnostics.OK   # nothing new since
    clock[0] += 10.0
    status = stats.status(counters)
    assert status["level"] == diagnostics.ERROR and "no output" in status["message"]
    assert stats.rate_hz() == 0.0
