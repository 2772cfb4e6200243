"""Camera extrinsics that follow the data (online/extrinsics.py): with ``auto`` a camera takes
TF where the data carries base_link -> its frame, the rig file where it does not (after a
set waited for TF), a TF that comes later wins, and a TF that differs from the rig file is
warned about once, naming the camera."""
import numpy as np
import pytest

from odg_ros.geometry import make_transform
from odg_ros.online.errors import BadInput
from odg_ros.online.extrinsics import CameraExtrinsics, transform_difference
from odg_ros.online.camera_calibration import Rig
from odg_ros.online.transforms import TransformBuffer
from testing.online import CAMS, RIG


def rotated_z(T, degrees):
    a = np.radians(degrees)
    return make_transform([np.cos(a / 2), 0, 0, np.sin(a / 2)], (0, 0, 0)) @ T


def shifted(T, metres):
    T = T.copy()
    T[0, 3] += metres
    return T


def auto(rig=RIG, source="auto"):
    tf = TransformBuffer()
    notes = []
    return CameraExtrinsics(source, "base_link", tf, rig,
                            lambda level, message: notes.append((level, message))), tf, notes


def outcome(extrinsics, camera, stamp=10.0, frame=None):
    try:
        return extrinsics(camera, frame or camera, stamp)
    except BadInput as error:
        return (error.kind, error.pending)


def test_transform_difference():
    T = RIG.cameras["CAM_FRONT"].sensor2ego
    assert transform_difference(T, T) == pytest.approx((0.0, 0.0), abs=1e-6)
    assert transform_difference(T, shifted(T, 0.07))[0] == pytest.approx(0.07)
    assert transform_difference(T, rotated_z(T, 0.8))[1] == pytest.approx(0.8, abs=1e-6)


def test_tf_where_the_data_carries_it_and_a_disagreement_warned_once_per_camera():
    extrinsics, tf, notes = auto()
    front, back = RIG.cameras["CAM_FRONT"].sensor2ego, RIG.cameras["CAM_BACK"].sensor2ego
    other_car = shifted(front, 0.12)
    tf.add("base_link", "CAM_FRONT", 0.0, other_car, static=True)
    tf.add("base_link", "CAM_BACK", 0.0, rotated_z(back, 0.3), static=True)   # within 0.5 deg
    for _ in range(3):
        assert np.array_equal(extrinsics("CAM_FRONT", "CAM_FRONT", 10.0), other_car)
        assert np.allclose(extrinsics("CAM_BACK", "CAM_BACK", 10.0), rotated_z(back, 0.3))
    assert len(notes) == 1 and notes[0][0] == "warning"
    assert notes[0][1].startswith("CAM_FRONT: TF base_link -> CAM_FRONT differs from the rig "
                                  "file by 0.120 m and 0.00 deg; using TF")
    assert extrinsics.sources(["CAM_FRONT", "CAM_BACK", "CAM_BACK_LEFT"]) == {
        "CAM_FRONT": "tf", "CAM_BACK": "tf", "CAM_BACK_LEFT": "none yet (waiting for TF)"}


def test_a_rotation_beyond_half_a_degree_is_a_disagreement():
    extrinsics, tf, notes = auto()
    T = rotated_z(RIG.cameras["CAM_FRONT"].sensor2ego, 0.7)
    tf.add("base_link", "cam_front_optical", 0.0, T, static=True)     # any frame name
    extrinsics("CAM_FRONT", "cam_front_optical", 10.0)
    assert len(notes) == 1 and "0.70 deg" in notes[0][1] and "CAM_FRONT" in notes[0][1]


def test_without_tf_a_camera_waits_then_settles_on_the_rig_file_once():
    extrinsics, tf, notes = auto()
    assert outcome(extrinsics, "CAM_FRONT") == ("missing_extrinsics", True)   # waits
    extrinsics.settle("CAM_FRONT", "CAM_FRONT")
    extrinsics.settle("CAM_FRONT", "CAM_FRONT")
    assert np.array_equal(extrinsics("CAM_FRONT", "CAM_FRONT", 10.0),
                          RIG.cameras["CAM_FRONT"].sensor2ego)
    assert notes == [("info", "CAM_FRONT: no TF base_link -> CAM_FRONT in the data: its "
                              "extrinsics come from the rig file")]
    assert extrinsics.sources(["CAM_FRONT"]) == {"CAM_FRONT": "rig file"}


def test_a_tf_that_comes_after_the_rig_file_wins_and_says_so():
    """/tf_static from a late publisher, or the first dynamic /tf seconds in."""
    extrinsics, tf, notes = auto()
    extrinsics.settle("CAM_FRONT", "CAM_FRONT")
    extrinsics("CAM_FRONT", "CAM_FRONT", 10.0)
    other_car = shifted(RIG.cameras["CAM_FRONT"].sensor2ego, 0.2)
    tf.add("base_link", "CAM_FRONT", 12.0, other_car)                   # dynamic, 2 Hz
    tf.add("base_link", "CAM_FRONT", 12.5, other_car)
    assert np.allclose(extrinsics("CAM_FRONT", "CAM_FRONT", 12.2), other_car)
    assert [level for level, _ in notes] == ["info", "warning", "warning"]
    assert "arrived after sets used the rig file; TF from now on" in notes[1][1]
    assert "differs from the rig file by 0.200 m" in notes[2][1]
    # beyond the newest dynamic transform: wait for the next one, no rig file meanwhile
    assert outcome(extrinsics, "CAM_FRONT", 12.8) == ("missing_extrinsics", True)
    extrinsics.settle("CAM_FRONT", "CAM_FRONT")
    assert outcome(extrinsics, "CAM_FRONT", 12.8) == ("missing_extrinsics", True)


def test_a_camera_on_tf_never_falls_back_silently_when_its_tf_goes():
    clock = [0.0]
    tf = TransformBuffer(cache_time=10.0, clock=lambda: clock[0])
    extrinsics = CameraExtrinsics("auto", "base_link", tf, RIG)
    tf.add("base_link", "CAM_FRONT", 1.0, RIG.cameras["CAM_FRONT"].sensor2ego)
    extrinsics("CAM_FRONT", "CAM_FRONT", 1.0)
    clock[0] = 30.0
    tf.add("map", "base_link", 30.0, np.eye(4))                         # prunes CAM_FRONT
    assert not tf.connected("base_link", "CAM_FRONT")
    extrinsics.settle("CAM_FRONT", "CAM_FRONT")
    assert outcome(extrinsics, "CAM_FRONT", 30.0) == ("missing_extrinsics", True)


def test_explicit_sources_and_a_camera_missing_from_the_rig_file():
    rig_only, tf, notes = auto(source="rig")
    tf.add("base_link", "CAM_FRONT", 0.0, shifted(RIG.cameras["CAM_FRONT"].sensor2ego, 1.0),
           static=True)
    assert np.array_equal(rig_only("CAM_FRONT", "CAM_FRONT", 1.0),
                          RIG.cameras["CAM_FRONT"].sensor2ego)
    assert rig_only.sources(["CAM_FRONT"]) == {"CAM_FRONT": "rig file"}
    tf_only = CameraExtrinsics("tf", "base_link", tf)
    assert outcome(tf_only, "CAM_BACK") == ("missing_extrinsics", True)
    tf_only.settle("CAM_BACK", "CAM_BACK")                              # tf: nothing to settle
    assert outcome(tf_only, "CAM_BACK") == ("missing_extrinsics", True)
    partial = Rig("base_link", {c: RIG.cameras[c] for c in CAMS if c != "CAM_BACK"})
    extrinsics, _, _ = auto(rig=partial)
    extrinsics.settle("CAM_BACK", "CAM_BACK")
    with pytest.raises(BadInput, match="CAM_BACK is not in the rig file and TF has no"):
        extrinsics("CAM_BACK", "CAM_BACK", 1.0)
    with pytest.raises(ValueError, match="expected one of: auto, rig, tf"):
        CameraExtrinsics("urdf", "base_link", tf)
