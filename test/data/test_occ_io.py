"""Occupancy GT loaders: Occ3D-nuScenes and Occ3D-Waymo -> (semantics, mask_lidar, mask_camera)."""
import numpy as np
import pytest

from odg_ros.classes import FREE_LABEL, WAYMO_FREE_LABEL
from odg_ros.data import occ_io

SHAPE = (200, 200, 16)


def _random_nuscenes(rng):
    semantics = rng.integers(0, 18, SHAPE, dtype=np.uint8)
    return semantics, rng.integers(0, 2, SHAPE, dtype=np.uint8), rng.integers(0, 2, SHAPE, dtype=np.uint8)


def test_nuscenes_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    semantics, mask_lidar, mask_camera = _random_nuscenes(rng)
    path = tmp_path / "labels.npz"
    np.savez_compressed(path, semantics=semantics, mask_lidar=mask_lidar, mask_camera=mask_camera)
    s, ml, mc = occ_io.load_occ3d_nuscenes(path)
    assert s.dtype == np.uint8 and ml.dtype == bool and mc.dtype == bool
    np.testing.assert_array_equal(s, semantics)
    np.testing.assert_array_equal(ml, mask_lidar == 1)
    np.testing.assert_array_equal(mc, mask_camera == 1)
    s2, _, _ = occ_io.load_occ(path, "nuscenes")
    np.testing.assert_array_equal(s2, semantics)


def test_waymo_mapping(tmp_path):
    rng = np.random.default_rng(1)
    # classes 0..14 plus the released files' free label 23
    voxel_label = rng.choice(np.r_[np.arange(15), 23], SHAPE).astype(np.uint8)
    origin = rng.integers(0, 2, SHAPE, dtype=np.uint8)
    final = rng.integers(0, 2, SHAPE, dtype=np.uint8)
    infov = rng.integers(0, 2, SHAPE, dtype=np.uint8)
    path = tmp_path / "000_04.npz"
    np.savez_compressed(path, voxel_label=voxel_label, origin_voxel_state=origin,
                        final_voxel_state=final, infov=infov)
    s, ml, mc = occ_io.load_occ3d_waymo(path)
    expected = np.where(voxel_label == 23, WAYMO_FREE_LABEL, voxel_label)
    np.testing.assert_array_equal(s, expected)
    assert s.max() == WAYMO_FREE_LABEL and (s == 0).any()
    np.testing.assert_array_equal(ml, origin == 1)
    np.testing.assert_array_equal(mc, (final == 1) & (infov == 1))
    # free label as a parameter (e.g. to put Waymo on the 17 = free convention)
    s17, _, _ = occ_io.load_occ3d_waymo(path, free_label=FREE_LABEL)
    np.testing.assert_array_equal(s17, np.where(voxel_label == 23, FREE_LABEL, voxel_label))
    # via the dataset switch
    s_any, _, mc_any = occ_io.load_occ(path, "waymo")
    np.testing.assert_array_equal(s_any, expected)
    np.testing.assert_array_equal(mc_any, mc)


def test_waymo_already_remapped_free(tmp_path):
    voxel_label = np.full(SHAPE, 15, np.uint8)
    voxel_label[0, 0, 0] = 3
    zeros = np.zeros(SHAPE, np.uint8)
    path = tmp_path / "f.npz"
    np.savez(path, voxel_label=voxel_label, origin_voxel_state=zeros, final_voxel_state=zeros,
             infov=zeros)
    s, ml, mc = occ_io.load_occ3d_waymo(path)
    assert s[0, 0, 0] == 3 and (s == WAYMO_FREE_LABEL).sum() == s.size - 1
    assert not ml.any() and not mc.any()


def test_bad_inputs_raise(tmp_path):
    with pytest.raises(FileNotFoundError):
        occ_io.load_occ3d_nuscenes(tmp_path / "nope.npz")
    path = tmp_path / "bad_keys.npz"
    np.savez(path, semantics=np.zeros(SHAPE, np.uint8))
    with pytest.raises(ValueError, match="missing keys"):
        occ_io.load_occ3d_nuscenes(path)
    path = tmp_path / "bad_label.npz"
    sem = np.zeros(SHAPE, np.uint8)
    sem[1, 2, 3] = 18
    np.savez(path, semantics=sem, mask_lidar=sem, mask_camera=sem)
    with pytest.raises(ValueError, match="outside"):
        occ_io.load_occ3d_nuscenes(path)
    path = tmp_path / "bad_grid.npz"
    small = np.zeros((100, 100, 16), np.uint8)
    np.savez(path, semantics=small, mask_lidar=small, mask_camera=small)
    with pytest.raises(ValueError, match="grid"):
        occ_io.load_occ3d_nuscenes(path)
    path = tmp_path / "bad_waymo.npz"
    lab = np.full(SHAPE, 23, np.uint8)
    lab[5, 5, 5] = 20  # neither a class nor free
    np.savez(path, voxel_label=lab, origin_voxel_state=lab, final_voxel_state=lab, infov=lab)
    with pytest.raises(ValueError, match="outside"):
        occ_io.load_occ3d_waymo(path)
    with pytest.raises(ValueError, match="unknown dataset"):
        occ_io.load_occ(path, "kitti")


def test_empty_occ():
    s, ml, mc = occ_io.empty_occ("nuscenes")
    assert s.shape == SHAPE and (s == FREE_LABEL).all() and not ml.any() and not mc.any()
    s, _, _ = occ_io.empty_occ("waymo")
    assert (s == WAYMO_FREE_LABEL).all()
