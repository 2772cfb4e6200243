"""Rays for the RayIoU tests, in the layout the ray caster takes."""
from __future__ import annotations

import numpy as np


def unravel(index, shape):
    return tuple(int(i) for i in np.unravel_index(index, shape))


def rays_from(origins, directions):
    """Every direction from every origin (voxel units) as float32 (start, end) pairs."""
    o = np.repeat(np.asarray(origins, dtype=np.float64), len(directions), axis=0)
    d = np.tile(np.asarray(directions, dtype=np.float64), (len(origins), 1))
    return o.astype(np.float32), (o + d).astype(np.float32)
