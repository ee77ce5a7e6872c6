"""SO(3) exp/log take values from sin/cos/atan2 and derivatives from the series-switched
formulas (``quaternion._exp_value`` / ``_exp_smooth`` and ``_log_value`` / ``_log_smooth``).
The two formulas must agree to a few ulp everywhere, including θ = 0, tiny θ and θ = π,
and the public functions must differentiate through the smooth ones."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.lie import _quaternion as quat

jax.config.update("jax_enable_x64", True)

ANGLES = np.concatenate([[0.0, 1e-30, 1e-12, 1e-8, 1e-4], np.linspace(0.01, np.pi, 40),
                         [np.pi - 1e-9, 2.5 * np.pi, 7.0]])


def _rotvecs(dtype):
    axes = np.random.default_rng(3).normal(size=(ANGLES.size, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    return jnp.asarray(axes * ANGLES[:, None], dtype)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_exp_value_and_smooth_formulas_agree(dtype):
    phi = _rotvecs(dtype)
    eps = np.finfo(dtype).eps
    np.testing.assert_allclose(quat._exp_value(phi), quat._exp_smooth(phi), rtol=0, atol=8 * eps)
    assert quat.exp(phi).dtype == dtype


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_log_value_and_smooth_formulas_agree(dtype):
    q = quat._exp_smooth(_rotvecs(dtype)[:-2])  # angles ≤ π: log returns the same vector
    q = jnp.concatenate([q, -q, jnp.asarray([[0.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0]], dtype)])
    eps = np.finfo(dtype).eps
    v, s = quat._log_value(q), quat._log_smooth(q)
    np.testing.assert_allclose(v, s, rtol=16 * eps, atol=16 * eps)
    # the π rotation about x: w = 0, log = (π, 0, 0)
    np.testing.assert_allclose(v[-1], [np.pi, 0.0, 0.0], rtol=2 * eps)


def test_derivatives_come_from_the_smooth_formulas():
    phi = _rotvecs(jnp.float64)
    for public, smooth in ((quat.exp, quat._exp_smooth), (quat.log, quat._log_smooth)):
        x = phi if public is quat.exp else quat.exp(phi)
        jf = jax.vmap(jax.jacfwd(public))(x)
        jr = jax.vmap(jax.jacrev(public))(x)
        np.testing.assert_array_equal(jf, jax.vmap(jax.jacfwd(smooth))(x))
        np.testing.assert_allclose(jr, jf, rtol=1e-13, atol=1e-15)
        h = jax.vmap(jax.hessian(lambda v: public(v).sum()))(x)
        assert np.all(np.isfinite(h))


def test_value_path_is_exact_at_zero():
    assert np.array_equal(quat.exp(jnp.zeros(3)), [0.0, 0.0, 0.0, 1.0])
    assert np.array_equal(quat.log(jnp.asarray([0.0, 0.0, 0.0, -2.0])), [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(jax.jacfwd(quat.exp)(jnp.zeros(3))[:3], 0.5 * np.eye(3))
