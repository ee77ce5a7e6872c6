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


def _exp_derivatives(fn, x, v):
    """(value, first, second, third) directional derivatives of fn at x along v."""
    def along(e):
        return fn(x + e * v)

    d1 = jax.jacfwd(along)
    d2 = jax.jacfwd(d1)
    d3 = jax.jacfwd(d2)
    return [f(jnp.float64(0.0)) for f in (along, d1, d2, d3)]


def test_exp_derivative_formulas_equal_the_switched_function_forms():
    """SO(3), SE(3) and SE(2)'s Exp take their derivatives from ``series.sinc_cos`` (one
    sincos per order, half-angle identities); the forms they replace, built from the
    separately switched functions (``series.sinc``, ``cos``, ``one_minus_cos_over_t``,
    ``theta_minus_sin_over_theta3``, each tested against mpmath), give the same first to
    third derivatives at θ = 0, tiny θ, around every switch point (θ = 1, 2) and large θ."""
    from jaxpose.lie import SE2, SE3, SO3, series

    def so3_ref(phi):
        t4 = 0.25 * jnp.sum(phi * phi)
        return jnp.concatenate([phi * 0.5 * series.sinc(t4), series.cos(t4)[None]])

    def se3_ref(xi):
        return jnp.concatenate([quat.jl_apply(xi[3:], xi[:3]), so3_ref(xi[3:])])

    def se2_ref(xi):
        t = xi[2] * xi[2]
        a, b = series.sinc(t), xi[2] * series.one_minus_cos_over_t(t)
        trans = jnp.stack([a * xi[0] - b * xi[1], b * xi[0] + a * xi[1]])
        return jnp.concatenate([trans, jnp.stack([jnp.cos(xi[2]), jnp.sin(xi[2])])])

    rng = np.random.default_rng(7)
    angles = [0.0, 1e-7, 0.5, 1.0 - 1e-9, 1.0 + 1e-9, 2.0 - 1e-9, 2.0 + 1e-9, 3.0, 9.5]
    cases = [(lambda p: SO3.exp(p).data, so3_ref, 3, slice(0, 3)),
             (lambda x: SE3.exp(x).data, se3_ref, 6, slice(3, 6)),
             (lambda x: SE2.exp(x).data, se2_ref, 3, slice(2, 3))]
    for ours, ref, dim, rot in cases:
        ours_d = jax.jit(lambda x, v, f=ours: _exp_derivatives(f, x, v))
        ref_d = jax.jit(lambda x, v, f=ref: _exp_derivatives(f, x, v))
        for angle in angles:
            x = rng.normal(size=dim)
            axis = x[rot] / np.linalg.norm(x[rot])
            x[rot] = angle * axis
            v = jnp.asarray(rng.normal(size=dim))
            for k, (a, b) in enumerate(zip(ours_d(jnp.asarray(x), v), ref_d(jnp.asarray(x), v),
                                           strict=True)):
                scale = max(1.0, float(jnp.max(jnp.abs(b))))
                np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * scale,
                                           err_msg=f"{dim}-dim Exp, θ={angle}, order {k}")
