"""The unrolled small-matrix helpers against LAPACK (numpy) references."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.geometry._registration import _det3
from jaxpose.geometry._util import spd_solve


@pytest.mark.parametrize("n", [1, 3, 4, 6])
@pytest.mark.parametrize("dtype,tol", [(np.float64, 1e-11), (np.float32, 1e-3)])
def test_spd_solve_matches_numpy_and_vmaps(rng, n, dtype, tol):
    m = rng.normal(size=(5, n + 3, n))
    a = m.transpose(0, 2, 1) @ m + 0.1 * np.eye(n)
    b = rng.normal(size=(5, n))
    x = jax.jit(jax.vmap(spd_solve))(jnp.asarray(a, dtype), jnp.asarray(b, dtype))
    assert x.dtype == dtype
    ref = np.linalg.solve(a, b[..., None])[..., 0]
    np.testing.assert_allclose(np.asarray(x), ref, rtol=tol, atol=tol)


def test_spd_solve_gradient_matches_finite_differences(rng):
    m = rng.normal(size=(6, 4))
    a = jnp.asarray(m.T @ m + np.eye(4))
    b = jnp.asarray(rng.normal(size=4))
    f = lambda b: jnp.sum(spd_solve(a, b) ** 2)  # noqa: E731
    g = jax.grad(f)(b)
    eps = 1e-6
    fd = [(f(b + eps * e) - f(b - eps * e)) / (2 * eps) for e in np.eye(4)]
    np.testing.assert_allclose(np.asarray(g), np.asarray(fd), rtol=1e-6, atol=1e-9)


def test_spd_solve_non_positive_pivot_gives_nan():
    x = spd_solve(jnp.asarray([[1.0, 2.0], [2.0, 1.0]]), jnp.asarray([1.0, 1.0]))
    assert not np.all(np.isfinite(np.asarray(x)))


def test_det3_matches_numpy_including_reflections(rng):
    m = rng.normal(size=(20, 3, 3))
    m[:5] = m[:5] * np.array([1.0, 1.0, -1.0])  # flip some handedness
    np.testing.assert_allclose(np.asarray(_det3(jnp.asarray(m))), np.linalg.det(m),
                               rtol=1e-12, atol=1e-12)
