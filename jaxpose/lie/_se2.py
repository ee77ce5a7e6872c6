"""SE(2): planar rigid transforms stored as ``[tx, ty, cos θ, sin θ]``.

Algebra se2: ``[ρx, ρy, θ]`` (translation first); Exp = (R(θ), V(θ)ρ) with
V(θ) = [[sinθ/θ, −(1−cosθ)/θ], [(1−cosθ)/θ, sinθ/θ]].
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp

from . import series
from ._base import Array, LieAlgebra, LieGroup, matvec, parts
from ._so2 import SO2, angle, normalize2, rot2, rotated


class se2(LieAlgebra):  # noqa: N801
    """se(2) element: ``data`` (..., 3) = ``[ρx, ρy, θ]``."""

    tangent_dim: ClassVar[int] = 3
    layout: ClassVar[str] = "[ρx, ρy, θ]"


def _v_coeffs(theta: Array) -> tuple[Array, Array]:
    """a = sinθ/θ and b = (1−cosθ)/θ, smooth at θ = 0, from the half-angle terms
    S = sin(θ/2)/(θ/2) and C = cos(θ/2) (one :func:`series.sinc_cos`, whose derivatives
    of every order share one sincos): a = S·C, b = θ·S²/2."""
    s, c = series.sinc_cos(0.25 * theta * theta)
    return series.computed_once(s * c, theta * (0.5 * s * s))


def _jl_column(xi: Array, *, principal: bool) -> Array:
    """The translation column w of Jl(ξ) = [[V, w], [0, 1]] (..., 2): w = [[B, A], [−A, B]]·ρ
    with A = (1 − cos θ)/θ², B = (θ − sin θ)/θ². ``principal=True`` promises |θ| ≤ π."""
    rx, ry, th = parts(xi)
    t = th * th
    a = series.select(series.one_minus_cos_over_t, principal)(t)
    b = th * series.select(series.theta_minus_sin_over_theta3, principal)(t)
    return jnp.stack([b * rx + a * ry, -a * rx + b * ry], -1)


def _with_column(block: Array, col: Array) -> Array:
    """[[block, col], [0, 1]] (..., 3, 3) from a (..., 2, 2) block and a (..., 2) column."""
    top = jnp.concatenate([block, col[..., None]], -1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], col.dtype), (*col.shape[:-1], 1, 3))
    return jnp.concatenate([top, bottom], -2)


def _perp(v: Array) -> Array:
    """[vy, −vx]: the SE(2) adjoint column, J·v with J = [[0, 1], [−1, 0]]."""
    x, y = parts(v)
    return jnp.stack([y, -x], -1)


class SE2(LieGroup):
    """SE(2) element: ``data`` (..., 4) = ``[tx, ty, cos θ, sin θ]``."""

    storage_dim: ClassVar[int] = 4
    tangent_dim: ClassVar[int] = 3
    matrix_dim: ClassVar[int] = 3
    point_dim: ClassVar[int] = 2
    layout: ClassVar[str] = "[tx, ty, cos θ, sin θ]"
    algebra: ClassVar[type[LieAlgebra]] = se2
    unit_slice: ClassVar[tuple[int, int]] = (2, 4)

    @staticmethod
    def _identity_data() -> Array:
        return jnp.array([0.0, 0.0, 1.0, 0.0])

    @staticmethod
    def _exp(xi: Array) -> Array:
        rx, ry, th = parts(xi)
        a, b = _v_coeffs(th)
        return jnp.stack([a * rx - b * ry, b * rx + a * ry, jnp.cos(th), jnp.sin(th)], -1)

    @staticmethod
    def _exp_linear(xi: Array) -> Array:
        rx, ry, th = parts(xi)
        return jnp.stack([rx, ry, jnp.ones_like(th), th], -1)

    @staticmethod
    def _exp_quadratic(xi: Array) -> Array:
        rx, ry, th = parts(xi)
        return jnp.stack([rx - 0.5 * th * ry, ry + 0.5 * th * rx, 1.0 - 0.5 * th * th, th], -1)

    @staticmethod
    def _log(x: Array) -> Array:
        tx, ty, c, s = parts(x)
        th = jnp.arctan2(s, c)
        h = series.half_cot_half_principal(th * th)  # |θ| ≤ π
        half = 0.5 * th
        return jnp.stack([h * tx + half * ty, -half * tx + h * ty, th], -1)

    @staticmethod
    def _compose(a: Array, b: Array) -> Array:
        (tax, tay, ca, sa), (tbx, tby, cb, sb) = parts(a), parts(b)
        rx, ry = rotated(ca, sa, tbx, tby)
        return jnp.stack([tax + rx, tay + ry, *rotated(ca, sa, cb, sb)], -1)

    @staticmethod
    def _inv(x: Array) -> Array:
        tx, ty, c, s = parts(x)  # (R⁻¹, −R⁻¹t)
        rx, ry = rotated(c, -s, tx, ty)
        return jnp.stack([-rx, -ry, c, -s], -1)

    @staticmethod
    def _act(x: Array, p: Array) -> Array:
        (tx, ty, c, s), (px, py) = parts(x), parts(p)
        rx, ry = rotated(c, s, px, py)
        return jnp.stack([rx + tx, ry + ty], -1)

    @staticmethod
    def _matrix(x: Array) -> Array:
        top = jnp.concatenate([rot2(x[..., 2:]), x[..., :2, None]], -1)
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], x.dtype), (*x.shape[:-1], 1, 3))
        return jnp.concatenate([top, bottom], -2)

    @staticmethod
    def _from_matrix(m: Array) -> Array:
        return jnp.concatenate([m[..., :2, 2], SO2._from_matrix(m[..., :2, :2])], -1)

    @staticmethod
    def _adj_matrix(x: Array) -> Array:
        top = jnp.concatenate([rot2(x[..., 2:]), _perp(x[..., :2])[..., None]], -1)
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], x.dtype), (*x.shape[:-1], 1, 3))
        return jnp.concatenate([top, bottom], -2)

    @staticmethod
    def _jl(xi: Array) -> Array:
        a, b = _v_coeffs(parts(xi)[2])
        v = jnp.stack([jnp.stack([a, -b], -1), jnp.stack([b, a], -1)], -2)
        return _with_column(v, _jl_column(xi, principal=False))

    @staticmethod
    def _jl_inv(xi: Array, principal: bool = False) -> Array:
        # [[V, w], [0, 1]]⁻¹ = [[V⁻¹, −V⁻¹w], [0, 1]] with V⁻¹ = [[h, θ/2], [−θ/2, h]].
        th = parts(xi)[2]
        h = series.select(series.half_cot_half, principal)(th * th)
        vinv = jnp.stack([jnp.stack([h, 0.5 * th], -1), jnp.stack([-0.5 * th, h], -1)], -2)
        return _with_column(vinv, -matvec(vinv, _jl_column(xi, principal=principal)))

    @staticmethod
    def _jl_inv_principal(xi: Array) -> Array:
        return SE2._jl_inv(xi, principal=True)

    @staticmethod
    def _jl_inv_principal_dual(xi: Array, y: Array) -> tuple[Array, Array, Array]:
        # ∂(Jl⁻¹(ξ)ᵀy)/∂ξ in closed form. Jl⁻¹ = [[V⁻¹, c], [0, 1]] with V⁻¹ = h·I + ½θ·P,
        # P = [[0, 1], [−1, 0]], h = (θ/2)cot(θ/2), and c = −V⁻¹·w = −θg·ρ − ½P·ρ,
        # g = (h − 1)/θ². With y = (a, b): Jl⁻¹ᵀy = (h·a − ½θ·P·a, c·a + b), so
        # ∂/∂θ of the first is 2θh′(t)·a − ½P·a; of the second, ∂/∂ρ = −θg·a + ½P·a and
        # ∂/∂θ = −(g + 2t·g′(t))·(ρ·a), t = θ²
        jac = SE2._jl_inv_principal(xi)
        rx, ry, th = parts(xi)
        ax, ay, _ = parts(y)
        t = th * th
        fh, fg = series.half_cot_half_principal, series.half_cot_half_minus_one_over_t_principal
        dh, g, dg = series.computed_once(fh.derivative(t), fg(t), fg.derivative(t))
        p_ax, p_ay = 0.5 * ay, -0.5 * ax  # ½P·a
        zero = jnp.zeros_like(th)
        d_theta = -(g + 2.0 * t * dg) * (rx * ax + ry * ay)
        rows = [[zero, zero, 2.0 * th * dh * ax - p_ax],
                [zero, zero, 2.0 * th * dh * ay - p_ay],
                [-th * g * ax + p_ax, -th * g * ay + p_ay, d_theta]]
        dual = jnp.stack([jnp.stack(r, -1) for r in rows], -2)
        jty = jnp.sum(jac * y[..., :, None], -2)
        return jac, jty, dual

    @staticmethod
    def _hat(xi: Array) -> Array:
        top = jnp.concatenate([SO2._hat(xi[..., 2:]), xi[..., :2, None]], -1)
        return jnp.concatenate([top, jnp.zeros_like(top[..., :1, :])], -2)

    @staticmethod
    def _normalize(x: Array) -> Array:
        return jnp.concatenate([x[..., :2], normalize2(x[..., 2:])], -1)

    def translation(self) -> Array:
        """Translation (…, 2)."""
        return self.data[..., :2]

    def rotation(self) -> SO2:
        """Rotation part as SO2 (data (…, 2) = ``[cos θ, sin θ]``)."""
        return SO2(self.data[..., 2:])

    def angle(self) -> Array:
        """Heading θ ∈ (−π, π] (…,)."""
        return angle(self.data[..., 2:])


se2.group = SE2
