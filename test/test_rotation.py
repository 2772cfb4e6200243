"""The rotation module against float64 references (scipy's Rotation and Slerp, NumPy norms):
quaternion normalising with its gradient, heading to quaternion and back, slerp, and their
hard cases (zero, denormal and huge quaternions, NaN, headings at +-pi, q against -q)."""
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from odg_ros.geometry import quaternion_to_matrix
from odg_ros.rotation import QUAT_NORM_MIN, SLERP_LINEAR_DOT, normalise_quaternions, slerp, \
    yaw_of, yaw_to_quaternion


def wxyz(rotation):
    x, y, z, w = rotation.as_quat()
    return np.array([w, x, y, z])


def same_rotation(q0, q1, atol=1e-12):
    """q and -q are one rotation."""
    return np.allclose(q0, q1, atol=atol) or np.allclose(q0, -np.asarray(q1), atol=atol)


# --- normalising (PyTorch) ---------------------------------------------------------------

def test_normalising_matches_the_float64_reference():
    q = torch.randn(500, 4, dtype=torch.float64) * torch.logspace(-8, 8, 500,
                                                                  dtype=torch.float64)[:, None]
    reference = q.numpy() / np.linalg.norm(q.numpy(), axis=-1, keepdims=True)
    np.testing.assert_allclose(normalise_quaternions(q).numpy(), reference, rtol=0, atol=1e-15)
    q32 = normalise_quaternions(q.float().view(5, 100, 4))      # any leading shape
    np.testing.assert_allclose(q32.view(500, 4).numpy(), reference, atol=1e-6)


def test_short_quaternions_become_the_identity_and_the_bound_keeps_its_direction():
    q = torch.tensor([[0.0, 0, 0, 0], [1e-300, 0, 0, 0], [0, 0, -0.5 * QUAT_NORM_MIN, 0],
                      [0, 0, QUAT_NORM_MIN, 0], [0, 3.0, 0, 4.0], [-2.0, 0, 0, 0]],
                     dtype=torch.float64, requires_grad=True)
    unit = normalise_quaternions(q)
    torch.testing.assert_close(unit.detach(), torch.tensor(
        [[1.0, 0, 0, 0], [1.0, 0, 0, 0], [1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, 0.6, 0, 0.8],
         [-1.0, 0, 0, 0]], dtype=torch.float64))
    (unit * torch.arange(24.0, dtype=torch.float64).view(6, 4)).sum().backward()
    assert torch.isfinite(q.grad).all()
    assert (q.grad[:3] == 0).all() and (q.grad[4] != 0).any()   # the identity is a constant


def test_huge_quaternions_do_not_overflow_and_nan_stays_nan():
    huge32 = normalise_quaternions(torch.tensor([[1e20, 1e20, 0, 0], [3e38, 0, 0, -3e38]]))
    torch.testing.assert_close(huge32, torch.tensor([[0.5 ** 0.5, 0.5 ** 0.5, 0, 0],
                                                     [0.5 ** 0.5, 0, 0, -0.5 ** 0.5]]))
    broken = normalise_quaternions(torch.tensor([[math.nan, 1.0, 0, 0], [math.inf, 0, 0, 0]]))
    assert torch.isnan(broken).any(dim=-1).all()       # never a valid-looking quaternion


def test_normalising_gradcheck():
    q = torch.randn(6, 4, dtype=torch.float64)
    q[1] *= 1e-2             # short and long: the gradient scales as 1 / |q|
    q[2] *= 1e3
    assert torch.autograd.gradcheck(normalise_quaternions, (q.requires_grad_(),))


# --- headings --------------------------------------------------------------------------

@pytest.mark.parametrize("yaw", [0.0, 0.3, -1.2, math.pi / 2, 3.0, math.pi, -math.pi,
                                 math.nextafter(math.pi, 0), math.nextafter(-math.pi, 0)])
def test_heading_to_quaternion_and_back(yaw):
    q = np.array(yaw_to_quaternion(yaw))
    assert same_rotation(q, wxyz(Rotation.from_euler("z", yaw)), atol=1e-15)
    back = yaw_of(quaternion_to_matrix(q))
    assert -math.pi < back <= math.pi or back == -math.pi  # arctan2's range
    assert abs(math.remainder(back - yaw, 2 * math.pi)) < 1e-12


def test_heading_of_a_matrix_matches_scipy():
    rng = np.random.default_rng(0)
    for yaw in rng.uniform(-math.pi, math.pi, 200):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
        assert yaw_of(T) == pytest.approx(yaw, abs=1e-12)
        assert yaw_of(T[:3, :3]) == yaw_of(T)


# --- slerp -----------------------------------------------------------------------------

def test_slerp_matches_scipy_on_random_pairs():
    rng = np.random.default_rng(1)
    for _ in range(200):
        r = Rotation.random(2, random_state=rng.integers(1 << 31))
        alpha = rng.uniform()
        reference = Slerp([0, 1], r)([alpha])[0]
        ours = slerp(wxyz(r[0]), wxyz(r[1]), alpha)
        assert np.linalg.norm(ours) == pytest.approx(1.0, abs=1e-15)
        assert same_rotation(ours, wxyz(reference), atol=1e-10)


def test_slerp_extrapolates_at_the_same_rate():
    rng = np.random.default_rng(2)
    for _ in range(50):
        r0, r1 = Rotation.random(2, random_state=rng.integers(1 << 31))
        alpha = rng.uniform(-1.0, 2.0)
        reference = r0 * Rotation.from_rotvec(alpha * (r0.inv() * r1).as_rotvec())
        assert same_rotation(slerp(wxyz(r0), wxyz(r1), alpha), wxyz(reference), atol=1e-10)


def test_slerp_hand_cases():
    q0 = np.array([1.0, 0, 0, 0])
    q90 = wxyz(Rotation.from_euler("z", 90, degrees=True))
    assert np.allclose(slerp(q0, q90, 0.5), wxyz(Rotation.from_euler("z", 45, degrees=True)))
    assert np.allclose(slerp(q0, q90, 0.0), q0) and np.allclose(slerp(q0, q90, 1.0), q90)
    assert np.allclose(slerp(q0, q90, 1.5), wxyz(Rotation.from_euler("z", 135, degrees=True)))
    # nearly identical quaternions (the lerp branch) stay unit and exact
    q_small = wxyz(Rotation.from_euler("x", 1e-4))
    assert np.isclose(np.linalg.norm(slerp(q0, q_small, 0.3)), 1.0)
    assert np.allclose(slerp(q0, q_small, 0.3), wxyz(Rotation.from_euler("x", 3e-5)), atol=1e-9)


def test_slerp_of_antipodal_quaternions_takes_the_short_way():
    q0 = wxyz(Rotation.from_euler("xyz", [0.3, -0.2, 2.0]))
    for alpha in (0.0, 0.25, 1.0, 1.5):
        assert np.allclose(slerp(q0, -q0, alpha), q0, atol=1e-15)   # one rotation: no motion
    q90 = wxyz(Rotation.from_euler("z", 90, degrees=True))
    half = slerp(np.array([1.0, 0, 0, 0]), -q90, 0.5)            # to +45 deg, not 45 - 180
    assert Rotation.from_quat(np.roll(half, -1)).as_euler("zyx")[0] == pytest.approx(np.pi / 4)


def test_slerp_across_its_lerp_branch():
    """Below the bound the normalised lerp is off by at most ~5e-7 (rad, at the bound: 0.05 mm
    at 100 m); above it slerp is exact."""
    q0 = np.array([1.0, 0, 0, 0])
    for angle, atol in ((0.999, 5e-7), (1.001, 1e-12)):   # around the bound, in its units
        theta = angle * 2 * math.acos(SLERP_LINEAR_DOT)
        q1 = wxyz(Rotation.from_euler("z", theta))
        expected = wxyz(Rotation.from_euler("z", 0.3 * theta))
        assert np.allclose(slerp(q0, q1, 0.3), expected, rtol=0, atol=atol)
