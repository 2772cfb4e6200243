"""Shared settings and small builders of the hard-case tests (test/**/test_hard_*.py).

Hypothesis runs derandomized (the same examples on every machine and every run, so CI is
deterministic), with few examples and no per-example deadline (2 busy CPU cores)."""
from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

HARD = settings(max_examples=25, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FEW = settings(HARD, max_examples=8)
FUZZ = settings(HARD, max_examples=150)     # cheap examples (bytes, stamp streams)


def log_uniform(lo: float, hi: float):
    """Floats spread evenly in log scale over [lo, hi] (both > 0), ends included."""
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: float(10.0 ** e)) | \
        st.sampled_from([lo, hi])


def rotation_matrix(axis, angle) -> np.ndarray:
    """Rodrigues: rotation by ``angle`` about ``axis`` (any length > 0)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def all_finite(*tensors) -> bool:
    return all(t is None or bool(torch.isfinite(t).all()) for t in tensors)
