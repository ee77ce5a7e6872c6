"""Sim(3): similarity transforms stored as ``[tx, ty, tz, qx, qy, qz, qw, s]`` (PyPose order).

Algebra sim3: ``[ρ(3), φ(3), σ]``; Exp = (W(φ, σ)ρ, Exp(φ), e^σ) with
W = ∫₀¹ e^{σu} R(uφ) du = a·I + b·[φ]× + c·[φ]×². ``a`` has a closed form; ``b`` and ``c``
are 1-D integrals of smooth (entire) integrands evaluated by 16-node Gauss–Legendre
quadrature, which is exact to float64 precision for |σ| + θ up to about 10 and has no
branches, so every derivative is finite. The Jacobians use the generic quadrature
Jl(ξ) = ∫₀¹ Ad(Exp(uξ)) du of the base class.
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp

from .. import _small_linalg as small_linalg
from . import _quaternion as quat
from . import series
from ._base import (
    GL_NODES,
    GL_WEIGHTS,
    Array,
    LieAlgebra,
    LieGroup,
    matvec,
    skew,
    small_matmul,
)
from ._rxso3 import RxSO3, cbrt_det
from ._so3 import SO3


class sim3(LieAlgebra):  # noqa: N801
    """sim(3) element: ``data`` (..., 7) = ``[ρx, ρy, ρz, φx, φy, φz, σ]``."""

    tangent_dim: ClassVar[int] = 7
    layout: ClassVar[str] = "[ρx, ρy, ρz, φx, φy, φz, σ]"


def w_matrix(phi: Array, sigma: Array) -> Array:
    """W(φ, σ) = ∫₀¹ e^{σu} Exp(uφ) du (…, 3, 3); ``sigma`` has shape (…,)."""
    t = series.safe_norm_sq(phi)[..., None]  # (..., 1)
    u = jnp.asarray(GL_NODES, phi.dtype)
    w = jnp.asarray(GL_WEIGHTS, phi.dtype)
    e = jnp.exp(sigma[..., None] * u) * w  # (..., N)
    # sin θ/θ = S·C and (1 − cos θ)/θ² = S²/2 at θ = u|φ| from the half-angle terms of one
    # series.sinc_cos (their derivatives of every order share one sincos)
    s, cos_half = series.sinc_cos(0.25 * t * u * u)
    b = jnp.sum(e * u * (s * cos_half), -1)
    c = jnp.sum(e * u * u * (0.5 * s * s), -1)
    a = series.expm1c(sigma)
    P = skew(phi)
    eye = jnp.eye(3, dtype=phi.dtype)
    return (a[..., None, None] * eye + b[..., None, None] * P
            + c[..., None, None] * small_matmul(P, P))


class Sim3(LieGroup):
    """Sim(3) element: ``data`` (..., 8) = ``[tx, ty, tz, qx, qy, qz, qw, s]``, s > 0."""

    storage_dim: ClassVar[int] = 8
    tangent_dim: ClassVar[int] = 7
    matrix_dim: ClassVar[int] = 4
    point_dim: ClassVar[int] = 3
    layout: ClassVar[str] = "[tx, ty, tz, qx, qy, qz, qw, s]"
    algebra: ClassVar[type[LieAlgebra]] = sim3
    unit_slice: ClassVar[tuple[int, int]] = (3, 7)
    scale_index: ClassVar[int | None] = 7

    @staticmethod
    def _identity_data() -> Array:
        return jnp.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0])

    @staticmethod
    def _exp(xi: Array) -> Array:
        rho, phi, sigma = xi[..., :3], xi[..., 3:6], xi[..., 6]
        t = matvec(w_matrix(phi, sigma), rho)
        return jnp.concatenate([t, quat.exp(phi), jnp.exp(sigma)[..., None]], -1)

    @staticmethod
    def _exp_linear(xi: Array) -> Array:
        one = jnp.ones_like(xi[..., :1])
        return jnp.concatenate([xi[..., :3], 0.5 * xi[..., 3:6], one, one + xi[..., 6:]], -1)

    @staticmethod
    def _exp_quadratic(xi: Array) -> Array:
        rho, phi, sigma = xi[..., :3], xi[..., 3:6], xi[..., 6:]
        t = rho + 0.5 * (sigma * rho + quat.cross(phi, rho))
        w = 1.0 - 0.125 * jnp.sum(phi * phi, -1, keepdims=True)
        return jnp.concatenate([t, 0.5 * phi, w, 1.0 + sigma + 0.5 * sigma * sigma], -1)

    @staticmethod
    def _log(x: Array) -> Array:
        phi = quat.log(x[..., 3:7])
        sigma = jnp.log(x[..., 7])
        w = w_matrix(phi, sigma)
        # W's entries grow as e^σ/σ: divided by the largest (a constant to autodiff, ρ does
        # not depend on it), the 3×3 adjugate and determinant neither overflow (ρ = 0 from
        # t/inf, float32 past σ ≈ 34) nor give inf/inf
        m = jax.lax.stop_gradient(jnp.max(jnp.abs(w), axis=(-2, -1), keepdims=True))
        rho = small_linalg.solve(w / m, x[..., :3, None] / m)[..., 0]
        return jnp.concatenate([rho, phi, sigma[..., None]], -1)

    @staticmethod
    def _compose(a: Array, b: Array) -> Array:
        t = a[..., :3] + a[..., 7:] * quat.rotate(a[..., 3:7], b[..., :3])
        q = quat.multiply(a[..., 3:7], b[..., 3:7])
        return jnp.concatenate([t, q, a[..., 7:] * b[..., 7:]], -1)

    @staticmethod
    def _inv(x: Array) -> Array:
        qi = quat.conjugate(x[..., 3:7])
        si = 1.0 / x[..., 7:]
        return jnp.concatenate([-si * quat.rotate(qi, x[..., :3]), qi, si], -1)

    @staticmethod
    def _act(x: Array, p: Array) -> Array:
        return x[..., 7:] * quat.rotate(x[..., 3:7], p) + x[..., :3]

    @staticmethod
    def _matrix(x: Array) -> Array:
        sr = x[..., 7:, None] * quat.to_matrix(x[..., 3:7])
        top = jnp.concatenate([sr, x[..., :3, None]], -1)
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], x.dtype), (*x.shape[:-1], 1, 4))
        return jnp.concatenate([top, bottom], -2)

    @staticmethod
    def _from_matrix(m: Array) -> Array:
        sr = m[..., :3, :3]
        s = cbrt_det(sr)
        q = quat.from_matrix(sr / s[..., None, None])
        return jnp.concatenate([m[..., :3, 3], q, s[..., None]], -1)

    @staticmethod
    def _adj_matrix(x: Array) -> Array:
        r = quat.to_matrix(x[..., 3:7])
        t = x[..., :3]
        s = x[..., 7:, None]
        z3 = jnp.zeros_like(r)
        z31 = jnp.zeros((*x.shape[:-1], 3, 1), x.dtype)
        row0 = jnp.concatenate([s * r, small_matmul(skew(t), r), -t[..., None]], -1)
        row1 = jnp.concatenate([z3, r, z31], -1)
        row2 = jnp.concatenate(
            [jnp.zeros((*x.shape[:-1], 1, 6), x.dtype), jnp.ones((*x.shape[:-1], 1, 1), x.dtype)],
            -1,
        )
        return jnp.concatenate([row0, row1, row2], -2)

    @classmethod
    def _jl_inv(cls, xi: Array) -> Array:
        """Jl⁻¹ from Jl's block-triangular form (Ad is block upper triangular in (ρ, φ, σ),
        so is its integral): Jl = [[X, Y, z], [0, J, 0], [0, 0, 1]] with J SO(3)'s Jl, so
        Jl⁻¹ = [[X⁻¹, −X⁻¹·Y·J⁻¹, −X⁻¹·z], [0, J⁻¹, 0], [0, 0, 1]] (X⁻¹ a 3×3 adjugate,
        J⁻¹ SO(3)'s closed form). No 7×7 LAPACK solve: batched, its derivatives deadlocked
        XLA:CPU on 2 cores (:mod:`jaxpose._small_linalg`)."""
        jl = cls._jl(xi)
        x_inv = small_linalg.inv(jl[..., :3, :3])
        j_inv = quat.jl_inv(xi[..., 3:6])
        coupling = -small_matmul(x_inv, jl[..., :3, 3:])  # −X⁻¹·[Y, z]
        row0 = jnp.concatenate([x_inv, small_matmul(coupling[..., :3], j_inv),
                                coupling[..., 3:]], -1)
        rest = jnp.zeros_like(jl[..., 3:, :]).at[..., :3, 3:6].set(j_inv).at[..., 3, 6].set(1.0)
        return jnp.concatenate([row0, rest], -2)

    @staticmethod
    def _hat(xi: Array) -> Array:
        m = skew(xi[..., 3:6]) + xi[..., 6:, None] * jnp.eye(3, dtype=xi.dtype)
        top = jnp.concatenate([m, xi[..., :3, None]], -1)
        return jnp.concatenate([top, jnp.zeros_like(top[..., :1, :])], -2)

    @staticmethod
    def _normalize(x: Array) -> Array:
        return jnp.concatenate([x[..., :3], quat.normalize(x[..., 3:7]), x[..., 7:]], -1)

    def translation(self) -> Array:
        """Translation (…, 3)."""
        return self.data[..., :3]

    def rotation(self) -> SO3:
        """Rotation part as SO3 (data (…, 4) = ``[qx, qy, qz, qw]``)."""
        return SO3(self.data[..., 3:7])

    def scale(self) -> Array:
        """Scale s (…,)."""
        return self.data[..., 7]

    def euler(self) -> Array:
        """Roll-pitch-yaw ``[r, p, y]`` (…, 3) of the rotation part."""
        return self.rotation().euler()

    def rxso3(self) -> RxSO3:
        """The rotation-and-scale part."""
        return RxSO3(self.data[..., 3:])


sim3.group = Sim3
