"""SE(3): rigid transforms stored as ``[tx, ty, tz, qx, qy, qz, qw]`` (PyPose order).

Algebra se3: twist ``[ρ(3), φ(3)]`` (translation part first), Exp(ξ) = (Exp(φ), Jl(φ)ρ).
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from .._precision import FULL
from . import _quaternion as quat
from . import series
from ._base import Array, LieAlgebra, LieGroup, skew, small_matmul
from ._so3 import SO3


class se3(LieAlgebra):  # noqa: N801
    """se(3) element: ``data`` (..., 6) = ``[ρx, ρy, ρz, φx, φy, φz]``."""

    tangent_dim: ClassVar[int] = 6
    layout: ClassVar[str] = "[ρx, ρy, ρz, φx, φy, φz]"


def _tq_by_products(x: Array) -> tuple[Array, Array]:
    """(t, q) of SE(3) storage (..., 7) as products with the identity's columns (exact for
    finite values; a non-finite component makes both parts non-finite). Slices transpose
    to pads that XLA:CPU fuses apart, each recomputing what the cotangents share; a product
    transposes to a product and is stored once. A Hessian through a least-squares solve
    over SE(3) residuals: with this in Log, 21 % fewer fused instructions (XLA 15 → 12.5 s);
    in ``compose`` too, its cold compile 17.5 → 15.6 s (interleaved in one process), while
    ``graph.solve`` on parking-garage ran within 1 % and its gradient 2–3 % slower (the
    products are kernels of their own; measured side by side in one process)."""
    e = jnp.eye(7, dtype=x.dtype)
    return (jnp.matmul(x, e[:, :3], precision=FULL), jnp.matmul(x, e[:, 3:], precision=FULL))


def _split(x: Array) -> tuple[Array, Array]:
    """(ρ, φ) of a twist (..., 6) by slices: products here (as :func:`_tq_by_products`)
    made the Hessian through least squares 20 % more fused code, not less."""
    return x[..., :3], x[..., 3:]


def _exp_smooth(xi: Array) -> Array:
    """Exp written for derivatives (NaN-free at every order), from the half-angle terms
    like :func:`_exp_value`: Jl(φ)ρ's coefficients and the quaternion from one
    :func:`quat.jl_coeffs` (one sincos per derivative order)."""
    rho, phi = _split(xi)
    a, b, s, c = quat.jl_coeffs(series.safe_norm_sq(phi))
    pv = quat.cross(phi, rho)
    trans = rho + a[..., None] * pv + b[..., None] * quat.cross(phi, pv)
    return jnp.concatenate([trans, phi * (0.5 * s)[..., None], c[..., None]], -1)


@quat.with_derivatives_of(_exp_smooth)
def _exp_value(xi: Array) -> Array:
    """Exp written for values from the half-angle terms s = sin(θ/2)/θ and c = cos(θ/2)
    the quaternion needs anyway: Jl(φ)ρ = ρ + a·φ×ρ + b·φ×(φ×ρ) with
    a = (1 − cos θ)/θ² = 2s² and b = (θ − sin θ)/θ³ = (1 − 2sc)/θ² (a polynomial below
    θ = 2). A third of the switched form's operations (both branches of two series
    switches), in every solver's retraction."""
    rho, phi = _split(xi)
    s, c = quat.half_angle_terms(phi)
    t = series.safe_norm_sq(phi)
    b = quat.theta_minus_sin_over_theta3(t, 2.0 * s * c)
    pv = quat.cross(phi, rho)
    trans = rho + (2.0 * s * s)[..., None] * pv + b[..., None] * quat.cross(phi, pv)
    return jnp.concatenate([trans, phi * s[..., None], c[..., None]], -1)


def q_block(rho: Array, phi: Array) -> Array:
    """Barfoot's Q(ρ, φ) (…, 3, 3): the off-diagonal block of the SE(3) left Jacobian."""
    t = series.safe_norm_sq(phi)
    c1, c2, c3 = (f(t)[..., None, None] for f in
                  (series.theta_minus_sin_over_theta3, series.se3_q_c2, series.se3_q_c3))
    P, R = skew(phi), skew(rho)
    PR, RP = small_matmul(P, R), small_matmul(R, P)
    PRP = small_matmul(PR, P)
    return (
        0.5 * R
        + c1 * (PR + RP + PRP)
        + c2 * (small_matmul(P, PR) + small_matmul(RP, P) - 3.0 * PRP)
        + c3 * (small_matmul(PRP, P) + small_matmul(P, PRP))
    )


def _jl_inv_from(rho: Array, phi: Array, t: Array, beta: Array, gamma: Array) -> Array:
    """Jl⁻¹(ξ) (..., 6, 6) on the principal range from ξ's parts (..., 3), t = |φ|² and the
    series coefficients β(t), γ(t) (..., ) (``SE3._jl_inv_principal``'s formula)."""
    # I − ½·ad + β·ad² + γ·ad⁴ (series.AD_PRINCIPAL) in 3×3 blocks, P = [φ]×, R = [ρ]×:
    # ad² = [[P², S], [0, P²]] with P² = φφᵀ − θ²I and S = PR + RP = ρφᵀ + φρᵀ − 2(φ·ρ)I,
    # ad⁴ = [[−θ²P², T], [0, −θ²P²]] with T = P²S + SP² = −2(φ·ρ)φφᵀ − θ²(ρφᵀ + φρᵀ)
    # + 4(φ·ρ)θ²I: outer products only (batched 6×6 products ran 3x slower on XLA:CPU)
    d = 2.0 * sum(phi[..., i] * rho[..., i] for i in range(3))  # 2(φ·ρ)
    beta, gamma = beta[..., None, None], gamma[..., None, None]
    t, d = t[..., None, None], d[..., None, None]
    eye = jnp.eye(3, dtype=phi.dtype)
    pp = phi[..., :, None] * phi[..., None, :]
    sym = rho[..., :, None] * phi[..., None, :] + phi[..., :, None] * rho[..., None, :]
    ji = eye - 0.5 * skew(phi) + (beta - gamma * t) * (pp - t * eye)
    q = (-0.5 * skew(rho) + beta * (sym - d * eye)
         + gamma * (-d * pp - t * sym + 2.0 * d * t * eye))  # d = 2(φ·ρ)
    return jnp.concatenate([jnp.concatenate([ji, q], -1),
                            jnp.concatenate([jnp.zeros_like(ji), ji], -1)], -2)


class SE3(LieGroup):
    """SE(3) element: ``data`` (..., 7) = ``[tx, ty, tz, qx, qy, qz, qw]``."""

    storage_dim: ClassVar[int] = 7
    tangent_dim: ClassVar[int] = 6
    matrix_dim: ClassVar[int] = 4
    point_dim: ClassVar[int] = 3
    layout: ClassVar[str] = "[tx, ty, tz, qx, qy, qz, qw]"
    algebra: ClassVar[type[LieAlgebra]] = se3
    unit_slice: ClassVar[tuple[int, int]] = (3, 7)

    @staticmethod
    def _identity_data() -> Array:
        return jnp.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])

    @staticmethod
    def _exp(xi: Array) -> Array:
        return _exp_value(xi)

    @staticmethod
    def _exp_linear(xi: Array) -> Array:
        return jnp.concatenate([xi[..., :3], 0.5 * xi[..., 3:], jnp.ones_like(xi[..., :1])], -1)

    @staticmethod
    def _exp_quadratic(xi: Array) -> Array:
        rho, phi = _split(xi)
        w = 1.0 - 0.125 * jnp.sum(phi * phi, -1, keepdims=True)
        return jnp.concatenate([rho + 0.5 * quat.cross(phi, rho), 0.5 * phi, w], -1)

    @staticmethod
    def _log(x: Array) -> Array:
        t, q = _tq_by_products(x)
        phi = quat.log(q)
        return jnp.concatenate([quat.jl_inv_apply(phi, t, principal=True), phi], -1)

    @staticmethod
    def _compose(a: Array, b: Array) -> Array:
        (ta, qa), (tb, qb) = _tq_by_products(a), _tq_by_products(b)
        return jnp.concatenate([ta + quat.rotate(qa, tb), quat.multiply(qa, qb)], -1)

    @staticmethod
    def _inv(x: Array) -> Array:
        qi = quat.conjugate(x[..., 3:])
        return jnp.concatenate([-quat.rotate(qi, x[..., :3]), qi], -1)

    @staticmethod
    def _act(x: Array, p: Array) -> Array:
        return quat.rotate(x[..., 3:], p) + x[..., :3]

    @staticmethod
    def _matrix(x: Array) -> Array:
        r = quat.to_matrix(x[..., 3:])
        top = jnp.concatenate([r, x[..., :3, None]], -1)
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], x.dtype), (*x.shape[:-1], 1, 4))
        return jnp.concatenate([top, bottom], -2)

    @staticmethod
    def _from_matrix(m: Array) -> Array:
        return jnp.concatenate([m[..., :3, 3], quat.from_matrix(m[..., :3, :3])], -1)

    @staticmethod
    def _adj_matrix(x: Array) -> Array:
        r = quat.to_matrix(x[..., 3:])
        z = jnp.zeros_like(r)
        return jnp.concatenate(
            [jnp.concatenate([r, small_matmul(skew(x[..., :3]), r)], -1),
             jnp.concatenate([z, r], -1)], -2
        )

    @staticmethod
    def _jl(xi: Array) -> Array:
        rho, phi = _split(xi)
        j = quat.jl(phi)
        q = q_block(rho, phi)
        z = jnp.zeros_like(j)
        return jnp.concatenate(
            [jnp.concatenate([j, q], -1), jnp.concatenate([z, j], -1)], -2
        )

    @staticmethod
    def _jl_inv(xi: Array) -> Array:
        rho, phi = _split(xi)
        ji = quat.jl_inv(phi)
        q = q_block(rho, phi)
        z = jnp.zeros_like(ji)
        return jnp.concatenate(
            # J⁻¹QJ⁻¹ by matmul: the unrolled small_matmul of two long fused chains made its
            # derivatives ~10x slower (jacfwd over 6275 elements: 600 ms against 23–60 ms)
            [jnp.concatenate([ji, -jnp.matmul(jnp.matmul(ji, q, precision=FULL), ji,
                                              precision=FULL)], -1),
             jnp.concatenate([z, ji], -1)], -2
        )

    @staticmethod
    def _jl_inv_principal(xi: Array) -> Array:  # formula: _jl_inv_from
        rho, phi = _split(xi)
        t = series.safe_norm_sq(phi)
        beta, gamma = series.computed_once(series.se3_jinv_ad2_principal(t),
                                           series.se3_jinv_ad4_principal(t))
        return _jl_inv_from(rho, phi, t, beta, gamma)

    @staticmethod
    def _jl_inv_principal_dual(xi: Array, y: Array) -> tuple[Array, Array, Array]:
        # ∂(Jl⁻¹(ξ)ᵀy)/∂ξ in closed form (a forward-mode Jacobian pushed six tangents through
        # the 6×6 matrix: 6 of parking-garage's 16 ms exact Hessian). With the blocks of
        # _jl_inv_principal, Jl⁻¹ = [[J, Q], [0, J]], J = I − ½[φ]× + c·(φφᵀ − tI),
        # c = β − γt, and y = (a, b): Jl⁻¹ᵀy = (Jᵀa, Qᵀa + Jᵀb), so
        # ∂/∂ξ = [[0, D(a)], [∂(Qᵀa)/∂ρ, ∂(Qᵀa)/∂φ + D(b)]] with D(u) = ∂(Jᵀu)/∂φ
        rho, phi = _split(xi)
        a, b = _split(y)
        t = series.safe_norm_sq(phi)
        fb, fg = series.AD_PRINCIPAL
        beta, gamma, dbeta, dgamma = series.computed_once(fb(t), fg(t), fb.derivative(t),
                                                         fg.derivative(t))
        jac = _jl_inv_from(rho, phi, t, beta, gamma)
        c, dc = beta - gamma * t, dbeta - dgamma * t - gamma
        eye = jnp.eye(3, dtype=xi.dtype)

        def dot(u: Array, v: Array) -> Array:
            return jnp.sum(u * v, -1)[..., None]

        def outer(u: Array, v: Array) -> Array:
            return u[..., :, None] * v[..., None, :]

        def scaled_eye(s: Array) -> Array:
            return s[..., None] * eye

        def d_j(u: Array) -> Array:  # ∂(Jᵀu)/∂φ, Jᵀu = u + ½φ×u + c·(φ(φ·u) − t·u)
            pu = dot(phi, u)
            return (-0.5 * skew(u) + outer(2.0 * dc[..., None] * (phi * pu - t[..., None] * u),
                                           phi)
                    + c[..., None, None] * (scaled_eye(pu) + outer(phi, u) - 2.0 * outer(u, phi)))

        # Qᵀa = ½ρ×a + β·A + γ·B, A = ρ(φ·a) + φ(ρ·a) − d·a,
        # B = −d·φ(φ·a) − t·(ρ(φ·a) + φ(ρ·a)) + 2dt·a, d = 2φ·ρ
        pa, ra, d = dot(phi, a), dot(rho, a), 2.0 * dot(phi, rho)
        tt = t[..., None]
        s_a = rho * pa + phi * ra
        big_a = s_a - d * a
        big_b = -d * phi * pa - tt * s_a + 2.0 * d * tt * a
        bb, gg = beta[..., None, None], gamma[..., None, None]
        t3 = tt[..., None]
        dq_rho = (-0.5 * skew(a)
                  + bb * (scaled_eye(pa) + outer(phi, a) - 2.0 * outer(a, phi))
                  + gg * (-2.0 * pa[..., None] * outer(phi, phi) - t3 * scaled_eye(pa)
                          - t3 * outer(phi, a) + 4.0 * t3 * outer(a, phi)))
        dq_phi = (outer(2.0 * dbeta[..., None] * big_a + 2.0 * dgamma[..., None] * big_b, phi)
                  + bb * (outer(rho, a) + scaled_eye(ra) - 2.0 * outer(a, rho))
                  + gg * (-2.0 * pa[..., None] * outer(phi, rho)
                          - d[..., None] * (scaled_eye(pa) + outer(phi, a))
                          - 2.0 * outer(s_a, phi) - t3 * (outer(rho, a) + scaled_eye(ra))
                          + 4.0 * t3 * outer(a, rho) + 4.0 * d[..., None] * outer(a, phi)))
        top = jnp.concatenate([jnp.zeros_like(dq_rho), d_j(a)], -1)
        bottom = jnp.concatenate([dq_rho, dq_phi + d_j(b)], -1)
        jty = jnp.sum(jac * y[..., :, None], -2)
        return jac, jty, jnp.concatenate([top, bottom], -2)

    @staticmethod
    def _hat(xi: Array) -> Array:
        rho, phi = _split(xi)
        top = jnp.concatenate([skew(phi), rho[..., None]], -1)
        return jnp.concatenate([top, jnp.zeros_like(top[..., :1, :])], -2)

    @staticmethod
    def _normalize(x: Array) -> Array:
        return jnp.concatenate([x[..., :3], quat.normalize(x[..., 3:])], -1)

    # -- components --------------------------------------------------------------------
    def translation(self) -> Array:
        """Translation (…, 3)."""
        return self.data[..., :3]

    def rotation(self) -> SO3:
        """Rotation part as SO3 (data (…, 4) = ``[qx, qy, qz, qw]``)."""
        return SO3(self.data[..., 3:])

    def euler(self) -> Array:
        """Roll-pitch-yaw ``[r, p, y]`` (…, 3) of the rotation part."""
        return self.rotation().euler()

    @classmethod
    def from_rotation_translation(cls, rotation: SO3, translation: Array) -> SE3:
        """SE3 from an SO3 ``rotation`` (…) and a ``translation`` (…, 3); batch shapes
        broadcast; an array translation's dtype promotes with the rotation's (as in
        ``compose``: float64 is not rounded to a float32 rotation's dtype), Python numbers
        and lists take the rotation's."""
        arrays = (np.ndarray, np.generic, jax.Array)
        t = jnp.asarray(translation)
        dtype = (jnp.result_type(rotation.dtype, t.dtype) if isinstance(translation, arrays)
                 else rotation.dtype)
        t, q = t.astype(dtype), rotation.data.astype(dtype)
        shape = jnp.broadcast_shapes(rotation.shape, t.shape[:-1])
        return cls(jnp.concatenate([jnp.broadcast_to(t, (*shape, 3)),
                                    jnp.broadcast_to(q, (*shape, 4))], -1))


se3.group = SE3
