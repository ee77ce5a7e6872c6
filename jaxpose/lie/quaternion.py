"""Raw unit-quaternion functions on arrays, PyPose/Eigen storage order ``[qx, qy, qz, qw]``.

All functions broadcast over leading axes and are smooth (NaN-free derivatives of any
order), including the SO(3) exponential and logarithm. Shapes: quaternions (..., 4),
rotation vectors and points (..., 3), matrices (..., 3, 3).
"""

from __future__ import annotations

import jax.numpy as jnp

from . import series
from .series import horner

Array = jnp.ndarray


def multiply(q1: Array, q2: Array) -> Array:
    """Hamilton product q1 ⊗ q2 (rotation q1 after q2)."""
    v1, w1 = q1[..., :3], q1[..., 3:]
    v2, w2 = q2[..., :3], q2[..., 3:]
    v = w1 * v2 + w2 * v1 + jnp.cross(v1, v2)
    w = w1 * w2 - jnp.sum(v1 * v2, -1, keepdims=True)
    return jnp.concatenate([v, w], -1)


def conjugate(q: Array) -> Array:
    """Inverse of a unit quaternion."""
    return jnp.concatenate([-q[..., :3], q[..., 3:]], -1)


def rotate(q: Array, p: Array) -> Array:
    """R(q) p for points p (..., 3): p + w·t + v × t with t = 2 v × p."""
    v, w = q[..., :3], q[..., 3:]
    t = 2.0 * jnp.cross(v, p)
    return p + w * t + jnp.cross(v, t)


def exp(phi: Array) -> Array:
    """SO(3) exponential of a rotation vector (..., 3) → unit quaternion (..., 4)."""
    t4 = series.safe_norm_sq(phi) * 0.25  # (θ/2)²
    s = 0.5 * series.sinc(t4)  # sin(θ/2)/θ
    w = series.cos(t4)  # cos(θ/2)
    return jnp.concatenate([phi * s[..., None], w[..., None]], -1)


_LOG_S0 = 0.04  # switch on s = (|v|/w)² where atan(x)/x has its series


def log(q: Array) -> Array:
    """SO(3) logarithm (..., 4) → rotation vector (..., 3) with angle in [0, π].

    Uses θ = 2·atan2(|v|, |w|) (accurate near θ = π) and a series of atan(x)/x near
    the identity; q and −q give the same result."""
    sign = jnp.where(q[..., 3:] < 0, -1.0, 1.0).astype(q.dtype)
    v = q[..., :3] * sign
    w = q[..., 3] * sign[..., 0]
    n2 = series.safe_norm_sq(v)
    small = n2 < _LOG_S0 * w * w
    # series branch: factor = (2/w)·atan(x)/x with x² = n²/w² < 0.04
    w_s = jnp.where(small, w, jnp.ones_like(w))
    s = jnp.where(small, n2 / (w_s * w_s), jnp.zeros_like(n2))
    f_series = 2.0 / w_s * horner(series._ATAN_COEFFS, s)
    # direct branch: factor = 2·atan2(n, w)/n with n bounded away from 0
    n = jnp.sqrt(jnp.where(small, jnp.ones_like(n2), n2))
    f_direct = 2.0 * jnp.arctan2(n, w) / n
    factor = jnp.where(small, f_series, f_direct)
    return v * factor[..., None]


def to_matrix(q: Array) -> Array:
    """Unit quaternion (..., 4) → rotation matrix (..., 3, 3)."""
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
        [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
        [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)],
    ]
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def from_matrix(m: Array) -> Array:
    """Rotation matrix (..., 3, 3) → unit quaternion with w ≥ 0 (Shepperd's method).

    The branch with the largest pivot is selected without boolean-mask assignment, and
    every branch is evaluated at a safe pivot, so derivatives stay finite. A matrix that
    is only approximately orthogonal is projected (the result is normalised)."""
    r00, r01, r02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    r10, r11, r12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    r20, r21, r22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    pivots = jnp.stack(
        [1 + r00 + r11 + r22, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22], -1
    )
    best = jnp.argmax(pivots, -1)
    # one candidate per pivot; 2·sqrt(pivot) = 4·(component)
    cands = []
    for k in range(4):
        p = pivots[..., k]
        safe = jnp.where(best == k, p, jnp.ones_like(p))
        r = jnp.sqrt(jnp.maximum(safe, jnp.finfo(m.dtype).tiny))  # = 2·|component k|
        inv = 0.5 / r
        if k == 0:
            c = [(r21 - r12) * inv, (r02 - r20) * inv, (r10 - r01) * inv, 0.5 * r]
        elif k == 1:
            c = [0.5 * r, (r01 + r10) * inv, (r02 + r20) * inv, (r21 - r12) * inv]
        elif k == 2:
            c = [(r01 + r10) * inv, 0.5 * r, (r12 + r21) * inv, (r02 - r20) * inv]
        else:
            c = [(r02 + r20) * inv, (r12 + r21) * inv, 0.5 * r, (r10 - r01) * inv]
        cands.append(jnp.stack(c, -1))
    onehot = (best[..., None] == jnp.arange(4))[..., None]
    q = jnp.sum(jnp.where(onehot, jnp.stack(cands, -2), 0.0), -2)
    q = q * jnp.where(q[..., 3:] < 0, -1.0, 1.0)
    return normalize(q)


def normalize(q: Array) -> Array:
    """Project onto the unit sphere."""
    return q / jnp.sqrt(series.safe_norm_sq(q))[..., None]


def jl(phi: Array) -> Array:
    """SO(3) left Jacobian I + A[φ]× + B[φ]×² (..., 3, 3)."""
    t = series.safe_norm_sq(phi)
    a = series.one_minus_cos_over_t(t)[..., None, None]
    b = series.theta_minus_sin_over_theta3(t)[..., None, None]
    return _poly_skew(phi, t, a, b)


def jl_inv(phi: Array) -> Array:
    """SO(3) inverse left Jacobian I − ½[φ]× + C[φ]×² (..., 3, 3)."""
    t = series.safe_norm_sq(phi)
    c = series.jinv_coeff(t)[..., None, None]
    return _poly_skew(phi, t, jnp.full_like(c, -0.5), c)


def _poly_skew(phi: Array, t: Array, a: Array, b: Array) -> Array:
    """I + a[φ]× + b[φ]×², using [φ]×² = φφᵀ − θ² I."""
    from .base import skew

    eye = jnp.eye(3, dtype=phi.dtype)
    outer = phi[..., :, None] * phi[..., None, :]
    return eye * (1.0 - b * t[..., None, None]) + a * skew(phi) + b * outer


def jl_apply(phi: Array, v: Array) -> Array:
    """Jl(φ) v without forming the matrix."""
    t = series.safe_norm_sq(phi)
    a = series.one_minus_cos_over_t(t)[..., None]
    b = series.theta_minus_sin_over_theta3(t)[..., None]
    pv = jnp.cross(phi, v)
    return v + a * pv + b * jnp.cross(phi, pv)


def jl_inv_apply(phi: Array, v: Array) -> Array:
    """Jl⁻¹(φ) v without forming the matrix."""
    t = series.safe_norm_sq(phi)
    c = series.jinv_coeff(t)[..., None]
    pv = jnp.cross(phi, v)
    return v - 0.5 * pv + c * jnp.cross(phi, pv)
