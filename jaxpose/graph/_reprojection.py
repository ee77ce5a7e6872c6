"""The BAL camera model as residual functions: one observation's reprojection residual,
its analytic Jacobians and the pieces of its pixel map (also used by the closed-form exact
Hessian of :mod:`jaxpose.graph._implicit`). Conventions in :mod:`jaxpose.graph._ba`:
``pose`` maps world to camera, ``pixel = f·(1 + k1‖p‖² + k2‖p‖⁴)·p`` with
``p = −P[:2] / P[2]``. Kept apart from the solver so that its derivative rule can use it
without an import cycle."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..lie import SE3

Array = jax.Array


def reprojection_residual(pose: SE3, intrinsics: Array, point: Array, z: Array) -> Array:
    """BAL reprojection residual (2,) of ONE observation ``z`` (pixels)."""
    return pixel(pose.act(point), intrinsics) - z


def pixel(pc: Array, intrinsics: Array) -> Array:
    """BAL pixel (2,) of a point ``pc`` (3,) in the camera frame, ``intrinsics`` [f, k1, k2]."""
    p = -pc[:2] / pc[2]
    r2 = p @ p
    f, k1, k2 = intrinsics[0], intrinsics[1], intrinsics[2]
    return f * (1.0 + r2 * (k1 + k2 * r2)) * p


def reprojection_jacobian(
    pose: SE3, intrinsics: Array, point: Array, z: Array
) -> tuple[Array, Array, Array, Array]:
    """Residual and analytic Jacobians of :func:`reprojection_residual`.

    Returns ``(r (2,), J_pose (2, 6), J_intrinsics (2, 3), J_point (2, 3))``; J_pose is
    with respect to the right perturbation ``pose · Exp([ρ, φ])``: ∂P/∂ρ = R,
    ∂P/∂φ = −R [X]×, ∂P/∂X = R."""
    rot = pose.rotation().matrix()
    pc = rot @ point + pose.translation()
    p, _, radial, _, dpix_dp, dp_dP, j_intr = pixel_terms(pc, intrinsics)
    residual = intrinsics[0] * radial * p - z
    dpix_dP = dpix_dp @ dp_dP
    j_point = dpix_dP @ rot
    skew = jnp.array([[0.0, -point[2], point[1]], [point[2], 0.0, -point[0]],
                      [-point[1], point[0], 0.0]], dtype=point.dtype)
    j_pose = jnp.concatenate([j_point, -j_point @ skew], axis=1)
    return residual, j_pose, j_intr, j_point


def pixel_terms(pc: Array, intrinsics: Array) -> tuple[Array, ...]:
    """The pieces of :func:`pixel` and its first derivatives at ``pc`` (3,):
    ``(p (2,), r², D, dD/dr², ∂pixel/∂p (2, 2), ∂p/∂P (2, 3), ∂pixel/∂[f, k1, k2] (2, 3))``
    with p = −P_xy/P_z, r² = |p|², D = 1 + k1·r² + k2·r⁴ and pixel = f·D·p."""
    inv_z = 1.0 / pc[2]
    p = -pc[:2] * inv_z
    r2 = p @ p
    f, k1, k2 = intrinsics[0], intrinsics[1], intrinsics[2]
    radial = 1.0 + r2 * (k1 + k2 * r2)
    dradial = k1 + 2.0 * k2 * r2
    zero = jnp.zeros_like(inv_z)
    dp_dP = jnp.stack([jnp.stack([-inv_z, zero, -p[0] * inv_z]),
                       jnp.stack([zero, -inv_z, -p[1] * inv_z])])
    dpix_dp = f * (radial * jnp.eye(2, dtype=p.dtype) + 2.0 * dradial * jnp.outer(p, p))
    j_intr = jnp.stack([radial * p, f * r2 * p, f * r2 * r2 * p], axis=1)
    return p, r2, radial, dradial, dpix_dp, dp_dP, j_intr


__all__ = ["pixel", "pixel_terms", "reprojection_jacobian", "reprojection_residual"]
