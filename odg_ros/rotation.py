"""Rotations: unit quaternions for the network and the renderer (PyTorch, differentiable),
heading to quaternion and back, and quaternion slerp for pose interpolation (NumPy, float64).

Quaternions are (w, x, y, z) and headings are rotations about z (geometry.py conventions).
"""
from __future__ import annotations

import math

import numpy as np
import torch

QUAT_NORM_MIN = 1e-12     # shorter quaternions have no usable direction -> identity
SLERP_LINEAR_DOT = 0.9995  # closer quaternions: sin(theta) ~ 0, normalised lerp is exact enough


def normalise_quaternions(rotations: torch.Tensor) -> torch.Tensor:
    """[..., 4] (w, x, y, z), any length -> unit quaternions [..., 4].

    A quaternion shorter than QUAT_NORM_MIN (zero, denormal) becomes the identity and gets a
    zero gradient, instead of a NaN or a gradient of ~1/|q|; one of exactly that length still
    has a direction, so it is kept (the same bound ``geometry.quaternion_to_matrix`` refuses
    below). Each quaternion is divided by its largest component first, so a huge one cannot
    overflow the norm (float32 squares overflow from ~1.8e19, and q / inf would be the zero
    quaternion, i.e. the identity).
    """
    with torch.no_grad():    # the output does not depend on the scale: no gradient through it
        largest = rotations.abs().amax(dim=-1, keepdim=True)
        scale = torch.where(largest > 0, largest, torch.ones_like(largest))
        tiny = largest * torch.linalg.vector_norm(rotations / scale, dim=-1,
                                                  keepdim=True) < QUAT_NORM_MIN
        scale = torch.where(tiny, torch.ones_like(scale), scale)   # no 1 / denormal
    identity = torch.zeros_like(rotations)
    identity[..., 0] = 1.0
    safe = torch.where(tiny, identity, rotations / scale)           # norm in [1, 2]
    return safe / torch.linalg.vector_norm(safe, dim=-1, keepdim=True)


def yaw_to_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation by ``yaw`` radians about z."""
    return (math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0))


def yaw_of(T) -> float:
    """Heading (rotation about z) in (-pi, pi] of a 4x4 transform or a 3x3 rotation."""
    R = np.asarray(T)[:3, :3]
    return float(np.arctan2(R[1, 0], R[0, 0]))


def slerp(q0, q1, alpha: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (w, x, y, z) along the shorter arc.

    ``alpha`` outside [0, 1] continues the rotation at the same angular rate (extrapolation).
    Written out rather than scipy's ``Slerp``: that one cannot extrapolate, and with its
    ``Rotation`` objects it costs about 20x as much a call, and the node interpolates a pose
    for every camera of every set.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(q0 @ q1)
    if dot < 0.0:           # q and -q are the same rotation; take the short way round
        q1, dot = -q1, -dot
    if dot > SLERP_LINEAR_DOT:
        q = q0 + alpha * (q1 - q0)
    else:
        theta = np.arccos(min(dot, 1.0))
        q = (np.sin((1.0 - alpha) * theta) * q0 + np.sin(alpha * theta) * q1) / np.sin(theta)
    return q / np.linalg.norm(q)
