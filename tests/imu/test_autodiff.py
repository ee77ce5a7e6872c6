"""Bias Jacobians equal autodiff of the deltas; jit, vmap and grad through the
preintegrator (w.r.t. measurements, biases and noise parameters, checked against finite
differences); the float32 path."""

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.imu import ImuPreintegrator, NavState, dead_reckon, preintegrate
from jaxpose.lie import SO3
from jaxpose.lie import _quaternion as quat

from . import reference as ref

N = 40
SIGMA_G = np.array([2e-3, 3e-3, 1.5e-3])
SIGMA_A = np.array([3e-2, 2e-2, 4e-2])
GYRO, ACC, DT = ref.random_window(7, N)
BG, BA = np.array([0.01, -0.02, 0.005]), np.array([0.1, -0.05, 0.2])


def _deltas(bias, scheme, prefix):
    """[Log(ΔR(b̂)ᵀΔR(b)), Δv(b), Δp(b)] — Forster's chart — at bias ``b`` (6,)."""
    kw = dict(bias_jacobians=False, scheme=scheme, prefix=prefix)
    base = preintegrate(GYRO, ACC, DT, gyro_bias=BG, acc_bias=BA, **kw)
    out = preintegrate(GYRO, ACC, DT, gyro_bias=bias[:3], acc_bias=bias[3:], **kw)
    phi = quat.log(quat.multiply(quat.conjugate(base.rot.data), out.rot.data))
    return jnp.concatenate([phi, out.vel, out.pos], -1)


@jax.jit
def _autodiff_jacobians(bias):
    return {s: jax.jacfwd(partial(_deltas, scheme=s, prefix=False))(bias)
            for s in ("manifold", "tangent")}


def test_bias_jacobians_equal_autodiff():
    auto = _autodiff_jacobians(jnp.concatenate([BG, BA]))
    for scheme, J in auto.items():
        out = preintegrate(GYRO, ACC, DT, gyro_bias=BG, acc_bias=BA, gyro_noise=SIGMA_G,
                           acc_noise=SIGMA_A, scheme=scheme)
        assert out.jac.shape == (9, 6)
        np.testing.assert_allclose(out.jac, J, rtol=1e-10, atol=1e-12, err_msg=scheme)
    # (the prefix Jacobians equal Forster's recurrences: test_preintegration.py)


def _loss(gyro, acc, dt, bg, ba, sg, sa):
    out = preintegrate(gyro, acc, dt, gyro_bias=bg, acc_bias=ba, gyro_noise=sg, acc_noise=sa,
                       integration_noise=1e-3)
    return (jnp.sum(out.pos**2) + jnp.sum(out.rot.data[:3]) + 1e3 * jnp.trace(out.cov)
            + jnp.sum(out.jac[6:9] ** 2))


@jax.jit
def _grads(args):
    return jax.grad(lambda a: _loss(*a))(args)


def test_grad_matches_finite_differences():
    """Reverse-mode gradient w.r.t. gyro, acc, dt, both biases and both noise densities,
    checked along random directions with central differences (float64)."""
    args = tuple(jnp.asarray(x) for x in (GYRO, ACC, DT, BG, BA, SIGMA_G, SIGMA_A))
    grads = _grads(args)
    rng = np.random.default_rng(0)
    f = jax.jit(lambda a: _loss(*a))
    for k, (x, gx) in enumerate(zip(args, grads, strict=True)):
        assert gx.shape == x.shape and np.all(np.isfinite(gx))
        u = rng.normal(size=x.shape) * (1e-4 if k == 2 else 1.0)
        h = 1e-6 * (1e-2 if k == 2 else 1.0)
        plus = tuple(a + h * u if i == k else a for i, a in enumerate(args))
        minus = tuple(a - h * u if i == k else a for i, a in enumerate(args))
        fd = (f(plus) - f(minus)) / (2 * h)
        np.testing.assert_allclose(float(jnp.vdot(gx, u)), float(fd), rtol=1e-5,
                                   err_msg=f"argument {k}")


def test_grad_wrt_module_noise_parameters():
    """The covariance is quadratic in the densities: d tr(Σ)/dσ = 2·tr(Σ(σ))/σ for a
    scalar scaling (σ_g, σ_a both scaled)."""
    imu = ImuPreintegrator(gyro_noise=SIGMA_G, acc_noise=SIGMA_A)

    @eqx.filter_jit
    def trace_and_grad(m):
        f = lambda m: jnp.trace(m(GYRO, ACC, DT).cov)  # noqa: E731
        return f(m), eqx.filter_grad(f)(m)

    tr, g = trace_and_grad(imu)
    # scaling both σ by s scales tr(Σ) by s²: d/ds at s=1 is 2·tr(Σ)
    dir_deriv = float(jnp.vdot(g.gyro_noise, imu.gyro_noise) + jnp.vdot(g.acc_noise,
                                                                          imu.acc_noise))
    np.testing.assert_allclose(dir_deriv, 2 * float(tr), rtol=1e-12)
    assert float(jnp.sum(jnp.abs(g.gravity))) == 0.0


def test_vmap_equals_per_window_calls():
    g = np.stack([GYRO, GYRO[::-1], 0.5 * GYRO])
    a = np.stack([ACC, ACC[::-1], ACC])
    one = lambda g, a: preintegrate(g, a, DT, gyro_bias=BG, acc_bias=BA,  # noqa: E731
                                    gyro_noise=SIGMA_G, acc_noise=SIGMA_A)
    vm = jax.jit(jax.vmap(one))(g, a)
    for k in range(3):
        single = one(g[k], a[k])
        for name in ("vel", "pos", "dt", "cov", "jac"):
            np.testing.assert_allclose(getattr(vm, name)[k], getattr(single, name),
                                       rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(vm.rot.data[k], single.rot.data, atol=1e-15)


@pytest.mark.parametrize("scheme", ["manifold", "tangent"])
def test_float32_path(scheme):
    """float32 inputs stay float32 and agree with float64 to single precision."""
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    kw = dict(gyro_noise=SIGMA_G, acc_noise=SIGMA_A, scheme=scheme)
    lo = preintegrate(f32(GYRO), f32(ACC), f32(DT), gyro_bias=f32(BG), acc_bias=f32(BA), **kw)
    hi = preintegrate(GYRO, ACC, DT, gyro_bias=BG, acc_bias=BA, **kw)
    for name in ("vel", "pos", "dt", "cov", "jac"):
        x = getattr(lo, name)
        assert x.dtype == jnp.float32, name
        y = np.asarray(getattr(hi, name))
        np.testing.assert_allclose(x, y, rtol=2e-4, atol=2e-5 * np.abs(y).max(), err_msg=name)
    assert lo.rot.data.dtype == jnp.float32
    np.testing.assert_allclose(lo.rot.data, hi.rot.data, atol=2e-6)
    if scheme == "manifold":
        init = NavState(SO3.identity(dtype=jnp.float32), np.zeros(3, np.float32),
                        np.zeros(3, np.float32))
        s = dead_reckon(f32(GYRO), f32(ACC), f32(DT), f32([0, 0, -9.81]), init)
        assert s.pos.dtype == jnp.float32
        R, v, p = ref.dead_reckoning(GYRO, ACC, DT, np.array([0.0, 0.0, -9.81]))[-1]
        np.testing.assert_allclose(s.pos[-1], p, atol=1e-5)
        np.testing.assert_allclose(s.vel[-1], v, atol=1e-5)
