"""Raw unit-quaternion functions on arrays, PyPose/Eigen storage order ``[qx, qy, qz, qw]``.

All functions broadcast over leading axes and are smooth (NaN-free derivatives of any
order), including the SO(3) exponential and logarithm. Shapes: quaternions (..., 4),
rotation vectors and points (..., 3), matrices (..., 3, 3).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp

from . import series
from ._base import max_abs, parts

Array = jnp.ndarray


def _stack(cs: list[Array]) -> Array:
    """Components (…,) stacked on a last axis. These kernels work on components
    (:func:`~jaxpose.lie._base.parts`) and stack once at the end: XLA:CPU vectorises
    elementwise code over the batch, but not reductions or gathers along a 3- or 4-wide
    minor axis."""
    return jnp.stack(jnp.broadcast_arrays(*cs), -1)


def multiply(q1: Array, q2: Array) -> Array:
    """Hamilton product q1 ⊗ q2 (rotation q1 after q2).

    Summed as (w1·v2 + w2·v1) + v1 × v2 and w1·w2 − v1·v2, each cross/dot product
    rounded on its own before the larger terms are added (less round-off than a flat
    left-to-right sum when the product is near the identity)."""
    x1, y1, z1, w1 = parts(q1)
    x2, y2, z2, w2 = parts(q2)
    return _stack([
        (w1 * x2 + x1 * w2) + (y1 * z2 - z1 * y2),
        (w1 * y2 + y1 * w2) + (z1 * x2 - x1 * z2),
        (w1 * z2 + z1 * w2) + (x1 * y2 - y1 * x2),
        w1 * w2 - (x1 * x2 + y1 * y2 + z1 * z2),
    ])


def cross(a: Array, b: Array) -> Array:
    """a × b for (..., 3) vectors, by components (``jnp.cross`` is a jitted call with
    reshapes and gathers that every derivative order copies)."""
    ax, ay, az = parts(a)
    bx, by, bz = parts(b)
    return _stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx])


def conjugate(q: Array) -> Array:
    """Inverse of a unit quaternion."""
    return q * jnp.asarray([-1.0, -1.0, -1.0, 1.0], q.dtype)


def rotate(q: Array, p: Array) -> Array:
    """R(q) p for points p (..., 3): (p + w·t) + v × t with t = 2 v × p (the small v × t
    term is rounded on its own before it is added)."""
    x, y, z, w = parts(q)
    px, py, pz = parts(p)
    tx, ty, tz = 2.0 * (y * pz - z * py), 2.0 * (z * px - x * pz), 2.0 * (x * py - y * px)
    return _stack([
        (px + w * tx) + (y * tz - z * ty),
        (py + w * ty) + (z * tx - x * tz),
        (pz + w * tz) + (x * ty - y * tx),
    ])


def _exp_smooth(phi: Array) -> Array:
    """The exponential written for derivatives: series switches in t = (θ/2)² make every
    derivative order NaN-free and accurate at θ = 0 (see :mod:`series`)."""
    x, y, z = parts(phi)
    t4 = 0.25 * (x * x + y * y + z * z)  # (θ/2)²
    sinc, w = series.sinc_cos(t4)  # sin(θ/2)/(θ/2), cos(θ/2)
    s = 0.5 * sinc  # sin(θ/2)/θ
    # one use per scalar coefficient: XLA:CPU would otherwise recompute the whole scalar
    # chain once per output component (it duplicates cheap producers into each consumer)
    return jnp.concatenate([phi * s[..., None], w[..., None]], -1)


def half_angle_terms(phi: Array) -> tuple[Array, Array]:
    """(sin(θ/2)/θ, cos(θ/2)) (...,) of rotation vectors (..., 3), θ = |φ|, for values
    (not derivatives): libm's sin and cos at h = θ/2 are accurate to the dtype for every
    h > 0 (h = 0 gives the limit), so no series is needed.

    h is computed as m·|φ/m|/2 with m = max |φᵢ|, so it does not overflow for any finite
    φ (|φ| ≳ 1e154 in float64, 1e19 in float32); beyond |φ| ≈ 1/eps the angle modulo 2π
    is not determined by the input's digits."""
    x, y, z = parts(phi)
    m = max_abs([x, y, z])
    r = 1.0 / jnp.where(m > 0, m, 1.0)
    xs, ys, zs = x * r, y * r, z * r
    h = m * jnp.sqrt(0.25 * (xs * xs + ys * ys + zs * zs))
    positive = h > 0
    h_safe = jnp.where(positive, h, 1.0)
    return jnp.where(positive, 0.5 * jnp.sin(h_safe) / h_safe, 0.5), jnp.cos(h)


def _exp_value(phi: Array) -> Array:
    """The exponential written for values (:func:`half_angle_terms`): a unit quaternion
    for every finite input."""
    s, w = half_angle_terms(phi)
    return jnp.concatenate([phi * s[..., None], w[..., None]], -1)


def _log_smooth(q: Array) -> Array:
    """The logarithm written for derivatives (branch-free, see :func:`series.quat_log_coeff`)."""
    x, y, z, w = parts(q)
    sign = jnp.where(w < 0, -1.0, 1.0).astype(q.dtype)
    f = sign * series.quat_log_coeff(x * x + y * y + z * z, w * sign)
    return _stack([x * f, y * f, z * f])


def _log_value(q: Array) -> Array:
    """The logarithm written for values: 2·atan2(n, |w|)/n, accurate for every n > 0.

    The quaternion is first divided by m = max |qᵢ|, so any nonzero finite quaternion
    (×1e200 or ×1e-200 included) gives the rotation vector of its direction."""
    m = max_abs(parts(q))
    q = q * (1.0 / jnp.where(m > 0, m, 1.0))[..., None]
    x, y, z, w = parts(q)
    n = jnp.sqrt(x * x + y * y + z * z)
    positive = n > 0
    n_safe = jnp.where(positive, n, 1.0)
    aw = jnp.abs(w)
    f = jnp.where(positive, 2.0 * jnp.arctan2(n_safe, aw) / n_safe, 2.0 / aw)
    f = jnp.where(w < 0, -f, f)
    # stacked like _log_smooth's result: where the two laid out their batch axis
    # differently under vmap, jax 0.10 failed to transpose grad(jit(vmap(log))) ("Sum of
    # sizes 3 must be equal to dimension 1"; jit(grad(...)) was fine)
    return _stack([x * f, y * f, z * f])


def with_derivatives_of(smooth: Callable[[Array], Array]):
    """Values from the decorated function, derivatives of every order from ``smooth``.

    Why two formulas: a series switch has to evaluate both branches, and XLA:CPU's cost
    model splits such polynomial-heavy loops over threads even at 1000 elements, where
    the hand-off costs more than the work (a 2-3x slower call). The value formulas use
    sin/cos/atan2 and are exact to the dtype; their derivatives would not be at θ → 0,
    which the smooth formulas handle. Both agree to a few ulp."""

    def wrap(value: Callable[[Array], Array]) -> Callable[[Array], Array]:
        # The optimization barriers were added to make each result one materialised array
        # (XLA:CPU copies a cheap producer, exp's polynomials say, into every consumer;
        # measured then 4x slower for the Jacobian of Log(Exp(x))). XLA:CPU in jax 0.10
        # removes barriers before fusion (none is left in the compiled program), so on the
        # CPU they no longer separate anything; series.computed_once does, where it pays.
        barrier = jax.lax.optimization_barrier
        f = jax.custom_jvp(lambda x: barrier(value(x)))

        def jvp(primals: tuple[Array], tangents: tuple[Array]) -> tuple[Array, Array]:
            y, dy = jax.jvp(smooth, primals, tangents)
            return barrier(y), barrier(dy)  # apart: reverse mode linearises the tangent alone

        f.defjvp(jvp)
        return functools.wraps(value)(f)

    return wrap


@with_derivatives_of(_exp_smooth)
def exp(phi: Array) -> Array:
    """SO(3) exponential of a rotation vector (..., 3) → unit quaternion (..., 4)."""
    return _exp_value(phi)


@with_derivatives_of(_log_smooth)
def log(q: Array) -> Array:
    """SO(3) logarithm (..., 4) → rotation vector (..., 3) with angle in [0, π].

    θ = 2·atan2(|v|, |w|) (accurate near 0 and π); q and −q give the same result.
    Derivatives come from :func:`series.quat_log_coeff` (branch-free, no atan2)."""
    return _log_value(q)


def to_matrix(q: Array) -> Array:
    """Unit quaternion (..., 4) → rotation matrix (..., 3, 3)."""
    x, y, z, w = parts(q)
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
    is only approximately orthogonal gives the normalised quaternion of that branch: a
    rotation within O(ε) of it, not the nearest one in the Frobenius norm."""
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
    """Project onto the unit sphere: q / |q|, computed as (q/m) / |q/m| with m = max |qᵢ|
    so that quaternions ×1e200 or ×1e-200 neither overflow nor underflow. The zero
    quaternion has no projection and gives NaN (``SO3(data, check=True)`` rejects it).
    m is held constant in derivatives (the projection does not depend on q's scale, so
    they are exact): through 1/m they were NaN below ×1e-160, where m² underflows."""
    m = jax.lax.stop_gradient(max_abs(parts(q)))
    q = q * (1.0 / jnp.where(m > 0, m, 1.0))[..., None]
    return q / jnp.sqrt(series.safe_norm_sq(q))[..., None]


# (θ − sin θ)/θ³ below t = θ² = 4 as one polynomial (its derivatives are polynomials);
# from there on (1 − S·C)/t loses at most a few ulp
THETA_MINUS_SIN_POLY = series.polynomial(series.theta_minus_sin_over_theta3, 4.0)


def jl_coeffs(t: Array) -> tuple[Array, Array, Array, Array]:
    """(a, b, S, C) of rotation angles θ from t = θ²: the left Jacobian's coefficients
    a = (1 − cos θ)/θ² = S²/2 and b = (θ − sin θ)/θ³ = (1 − S·C)/θ² (a polynomial below
    θ = 2) from the half-angle terms S = sin(θ/2)/(θ/2), C = cos(θ/2) of one
    :func:`series.sinc_cos` (their derivatives of every order share one sincos)."""
    s, c = series.sinc_cos(0.25 * t)
    return 0.5 * s * s, theta_minus_sin_over_theta3(t, s * c), s, c


def theta_minus_sin_over_theta3(t: Array, sinc: Array) -> Array:
    """(θ − sin θ)/θ³ from t = θ² and sinc = sin θ/θ: :data:`THETA_MINUS_SIN_POLY` below
    θ = 2, (1 − sinc)/t from there on (double-``where``)."""
    t0 = THETA_MINUS_SIN_POLY.t0
    small = t < t0
    return jnp.where(small, THETA_MINUS_SIN_POLY(jnp.where(small, t, jnp.zeros_like(t))),
                     (1.0 - sinc) / jnp.where(small, jnp.full_like(t, t0), t))


def jl(phi: Array) -> Array:
    """SO(3) left Jacobian I + A[φ]× + B[φ]×² (..., 3, 3)."""
    t = series.safe_norm_sq(phi)
    a, b, _, _ = jl_coeffs(t)
    return _poly_skew(phi, t, a[..., None, None], b[..., None, None])


def jl_inv(phi: Array, *, principal: bool = False) -> Array:
    """SO(3) inverse left Jacobian I − ½[φ]× + C[φ]×² (..., 3, 3). ``principal=True``
    promises |φ| ≤ π (as :func:`jl_inv_apply`)."""
    t = series.safe_norm_sq(phi)
    c = series.select(series.jinv_coeff, principal)(t)[..., None, None]
    return _poly_skew(phi, t, jnp.full_like(c, -0.5), c)


def _poly_skew(phi: Array, t: Array, a: Array, b: Array) -> Array:
    """I + a[φ]× + b[φ]×², using [φ]×² = φφᵀ − θ² I."""
    from ._base import skew

    eye = jnp.eye(3, dtype=phi.dtype)
    outer = phi[..., :, None] * phi[..., None, :]
    return eye * (1.0 - b * t[..., None, None]) + a * skew(phi) + b * outer


def jl_apply(phi: Array, v: Array) -> Array:
    """Jl(φ) v without forming the matrix."""
    a, b, _, _ = jl_coeffs(series.safe_norm_sq(phi))
    pv = cross(phi, v)
    return v + a[..., None] * pv + b[..., None] * cross(phi, pv)


def jl_inv_apply(phi: Array, v: Array, *, principal: bool = False) -> Array:
    """Jl⁻¹(φ) v without forming the matrix. ``principal=True`` promises |φ| ≤ π (φ from
    :func:`log`) and evaluates the coefficient as one polynomial (smaller programs)."""
    t = series.safe_norm_sq(phi)
    c = series.select(series.jinv_coeff, principal)(t)[..., None]
    pv = cross(phi, v)
    return v - 0.5 * pv + c * cross(phi, pv)
