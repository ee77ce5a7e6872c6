"""GTSAM's default ("tangent") preintegration scheme (internal).

GTSAM 4.x builds ``PreintegratedImuMeasurements`` on ``TangentPreintegration`` by
default: the rotation is kept as a rotation vector θ (ΔR = Exp(θ)) and advanced to
first order, ``θ ← θ + Jr(θ)⁻¹·ω·dt``, instead of Forster et al.'s exact
``ΔR ← ΔR·Exp(ω dt)``. The two agree to O(dt) per interval. The state here is GTSAM's
``[θ, p, v]`` with additive errors; its covariance and bias Jacobians are propagated with
the exact Jacobians A, B, C of one update (forward-mode autodiff), exactly as GTSAM's
``UpdatePreintegrated`` does analytically, and converted to Forster's chart at the end
(``δφ = Jr(θ)·δθ``, reordered to ``[φ, v, p]``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..lie import _quaternion as quat
from ._core import Delta, Noise

Array = jax.Array


def _update(x: Array, a: Array, w: Array, dt: Array) -> Array:
    """One GTSAM tangent update of ``x = [θ, p, v]`` (9,) with body acc ``a``, rate ``w``."""
    theta, pos, vel = x[0:3], x[3:6], x[6:9]
    w_tangent = quat.jl_inv_apply(-theta, w)  # Jr(θ)⁻¹ ω
    a_nav = quat.rotate(quat.exp(theta), a)
    return jnp.concatenate(
        [theta + w_tangent * dt, pos + vel * dt + a_nav * (0.5 * dt * dt), vel + a_nav * dt]
    )


def preintegrate(
    omega: Array, acc: Array, dt: Array, noise: Noise | None, with_jac: bool, prefix: bool
) -> Delta:
    """Bias-corrected samples (N, 3), dt (N,) → Delta (final, or all N prefixes)."""
    dtype = omega.dtype
    with_cov = noise is not None
    eye3 = jnp.eye(3, dtype=dtype)

    def step(carry, sample):
        x, cov, h = carry
        a, w, d = sample
        x_new = _update(x, a, w, d)
        if not (with_cov or with_jac):
            return (x_new, cov, h), (x_new, cov, h)
        jx, ja, jw = jax.jacfwd(_update, argnums=(0, 1, 2))(x, a, w, d)
        if with_cov:
            cov = (
                jx @ cov @ jx.T
                + ja @ ((noise.acc / d)[:, None] * ja.T)
                + jw @ ((noise.gyro / d)[:, None] * jw.T)
            )
            cov = cov.at[3:6, 3:6].add(eye3 * (noise.integration * d))
        if with_jac:
            h = jx @ h - jnp.concatenate([jw, ja], -1)  # columns [b_g, b_a]
        return (x_new, cov, h), (x_new, cov, h)

    init = (
        jnp.zeros(9, dtype),
        jnp.zeros((9, 9), dtype) if with_cov else None,
        jnp.zeros((9, 6), dtype) if with_jac else None,
    )
    last, hist = jax.lax.scan(step, init, (acc, omega, dt))
    x, cov, h = hist if prefix else last
    t = jnp.cumsum(dt) if prefix else jnp.sum(dt)
    theta, pos, vel = x[..., 0:3], x[..., 3:6], x[..., 6:9]
    # [θ, p, v] additive → [φ, v, p] with ΔR(θ + δθ) ≈ ΔR(θ)·Exp(Jr(θ) δθ)
    jr = quat.jl(-theta)
    z = jnp.zeros_like(jr)
    i3 = jnp.broadcast_to(eye3, jr.shape)
    tmat = jnp.concatenate(
        [
            jnp.concatenate([jr, z, z], -1),
            jnp.concatenate([z, z, i3], -1),
            jnp.concatenate([z, i3, z], -1),
        ],
        -2,
    )
    cov_f = None if cov is None else tmat @ cov @ jnp.swapaxes(tmat, -1, -2)
    jac_f = None if h is None else tmat @ h
    return Delta(quat.exp(theta), vel, pos, t, cov_f, jac_f)
