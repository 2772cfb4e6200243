"""odg_node's set-up without ROS (online/node_setup.py), which testing/bag_pipeline.py shares:
every geometry parameter reaches the TF buffer and the pipeline, and intrinsics_source rig
gives the pipeline each camera's calibration from the rig file at start (no CameraInfo)."""
from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest
import yaml

from odg_ros.online import node_setup
from odg_ros.online.camera_calibration import IntrinsicsRange
from odg_ros.online.parameters import validate
from odg_ros.online.pipeline import PipelineSettings
from odg_ros.online.predictor import OnlinePredictor
from odg_ros.resources import resource_path
from testing.online import CAMS, RIG, make_model


@pytest.fixture(scope="module")
def predictor():
    model, cfg = make_model()
    return OnlinePredictor(model, cfg, "cpu")


def test_the_settings_reach_the_tf_buffer_and_the_pipeline(predictor):
    p = validate({"max_pose_gap": 0.8, "pose_wait": 0.3, "max_pose_extrapolation": 0.02,
                  "tf_cache_time": 4.0, "slop": 0.04})
    found = node_setup.sources(p, list(CAMS))
    assert (found.tf.max_interpolation_gap, found.tf.max_extrapolation,
            found.tf.cache_time) == (0.8, 0.02, 4.0)
    assert found.extrinsics.source == "auto" and found.intrinsics is None
    pipeline = node_setup.build_pipeline(predictor, p, list(CAMS), found)
    try:
        s = pipeline.settings
        assert (s.max_pose_gap, s.pose_wait, s.pose_max_extrapolation, s.slop) == \
            (0.8, 0.3, 0.02, 0.04)
        assert pipeline.waiting.wait == 0.3 and pipeline.poses.max_interpolation_gap == 0.8
        assert not pipeline._camera_info
    finally:
        pipeline.close()


def test_every_pipeline_setting_is_its_node_parameter():
    """Each setting but time_jump is its own parameter (by default the schema's default)."""
    given = PipelineSettings.from_parameters(CAMS, validate({
        "slop": 0.07, "max_future_stamp": 0.9, "max_pose_extrapolation": 0.02,
        "max_pose_gap": 0.8, "pose_wait": 0.3, "min_focal_length": 0.2, "max_focal_length": 10.0,
        "max_principal_point_offset": 0.3, "max_speed": 50.0, "max_acceleration": 20.0,
        "max_image_pixels": 1000000}))
    assert {f.name: getattr(given, f.name) for f in fields(PipelineSettings)} == {
        "camera_names": CAMS, "slop": 0.07, "max_future": 0.9, "pose_max_extrapolation": 0.02,
        "max_pose_gap": 0.8, "pose_wait": 0.3, "intrinsics": IntrinsicsRange(0.2, 10.0, 0.3),
        "max_speed": 50.0, "max_acceleration": 20.0, "max_image_pixels": 1000000,
        "time_jump": 1.0}
    default = PipelineSettings.from_parameters(CAMS, pose_wait=5.0)
    assert (default.slop, default.max_speed, default.pose_wait) == (0.05, 70.0, 5.0)


def test_intrinsics_from_the_rig_file(predictor):
    p = validate({"intrinsics_source": "rig", "extrinsics_source": "tf"})
    found = node_setup.sources(p, list(CAMS))
    assert found.camera_frames() == {RIG.cameras[c].frame_id for c in CAMS}
    assert found.extrinsics.rig is None           # extrinsics from TF only
    pipeline = node_setup.build_pipeline(predictor, p, list(CAMS), found)
    try:
        for camera in CAMS:
            given = pipeline._camera_info[camera]
            assert np.array_equal(given.intrinsics, RIG.cameras[camera].intrinsics)
            assert given.image_hw == RIG.cameras[camera].image_hw
            assert given.frame_id == RIG.cameras[camera].frame_id
    finally:
        pipeline.close()


def test_a_rig_file_that_cannot_give_the_intrinsics_is_one_line(predictor, tmp_path):
    lower = [c.lower() for c in CAMS]
    with pytest.raises(ValueError, match=r"cameras \['cam_front', .* are not in the rig file "
                       r"config/rig_nuscenes.yaml \(intrinsics_source rig; it has"):
        node_setup.sources(validate({"intrinsics_source": "rig", "camera_names": lower}),
                           lower)
    # a camera-info node only warns: its extrinsics may come from TF
    notes = []
    node_setup.sources(validate({"camera_names": lower}), lower,
                       lambda level, message: notes.append(level))
    assert notes == ["warning"]
    # intrinsics the rig file accepts but the node's bounds do not
    rig = yaml.safe_load(resource_path("config/rig_nuscenes.yaml").read_text())
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(rig))
    p = validate({"intrinsics_source": "rig", "rig_file": str(path),
                  "max_focal_length": 0.2})
    with pytest.raises(ValueError, match=r"rig.yaml, camera CAM_FRONT \(intrinsics_source "
                       r"rig\): CameraInfo .* focal length"):
        node_setup.build_pipeline(predictor, p, list(CAMS), node_setup.sources(p, list(CAMS)))
