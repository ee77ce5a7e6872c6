"""Shared set-up for the geometry tests.

float64 is enabled for the session; float32 paths pass float32 arrays explicitly.
Compilation dominates the run time on CPU, so each test jits one function per
configuration and reuses it. PyPose cross-checks are marked ``peer`` and skip when
PyPose is not installed.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def random_rotation(rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Uniform random rotation matrices (numpy, independent of jaxpose)."""
    shape = () if n is None else (n,)
    q = rng.normal(size=(*shape, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def se3_from_rt(r: np.ndarray, t: np.ndarray):
    """jaxpose SE3 from numpy rotation matrices and translations."""
    from jaxpose.lie import SE3

    m = np.zeros((*r.shape[:-2], 4, 4))
    m[..., :3, :3] = r
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return SE3.from_matrix(m)


def pypose():
    """The pypose module, or skip the test."""
    return pytest.importorskip("pypose")
