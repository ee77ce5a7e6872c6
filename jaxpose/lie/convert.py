"""Conversions between rotation representations (arrays in, arrays out).

Euler angles are roll-pitch-yaw ``[r, p, y]`` with R = Rz(y)·Ry(p)·Rx(r), as in PyPose's
``euler2SO3`` / ``LieTensor.euler``. Quaternions are scalar-last ``[qx, qy, qz, qw]``
unless the name says ``wxyz``.
"""

from __future__ import annotations

import jax.numpy as jnp

from . import _quaternion as quat

Array = jnp.ndarray


def euler_to_quaternion(euler: Array) -> Array:
    """Roll-pitch-yaw (…, 3) → quaternion (…, 4)."""
    hr, hp, hy = (0.5 * euler[..., i] for i in range(3))
    cr, sr = jnp.cos(hr), jnp.sin(hr)
    cp, sp = jnp.cos(hp), jnp.sin(hp)
    cy, sy = jnp.cos(hy), jnp.sin(hy)
    return jnp.stack(
        [
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ],
        -1,
    )


def quaternion_to_euler(q: Array) -> Array:
    """Quaternion (…, 4) → roll-pitch-yaw (…, 3); pitch in [−π/2, π/2], roll and yaw in
    [−π, π] (scipy's ``as_euler("xyz")``).

    Half-angle form of Bernardes & Viollet (PLoS ONE 2022, as scipy): pitch from an
    ``atan2`` of two norms (accurate up to ±π/2, unlike ``arcsin``), roll and yaw from
    ``(b, a)`` and ``(d, c)``, each well conditioned on one side of the lock, so the
    angles rebuild R to rounding at and near gimbal lock. At the lock (pitch within
    rounding of ±π/2: √(a² + b²) ≤ ε·√(c² + d²) or the reverse) only roll ∓ yaw is
    defined: yaw is set to 0 as scipy does. Not differentiable there
    (gradients are finite, not meaningful)."""
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    a, b, c, d = w - y, x + z, w + y, z - x
    n_ab, n_cd = a * a + b * b, c * c + d * d
    zero_ab, zero_cd = n_ab == 0, n_cd == 0
    # double where: no NaN from atan2(0, 0) or sqrt'(0) at the lock
    n_ab = jnp.where(zero_ab, 0.0, jnp.sqrt(jnp.where(zero_ab, 1.0, n_ab)))
    n_cd = jnp.where(zero_cd, 0.0, jnp.sqrt(jnp.where(zero_cd, 1.0, n_cd)))
    pitch = 2.0 * jnp.arctan2(n_cd, n_ab) - 0.5 * jnp.pi
    # the lock: pitch within rounding of ±π/2, where roll ± yaw is rounding noise (a
    # rotation built from exact matrices at the lock rarely gives n_ab or n_cd exactly 0)
    eps = jnp.finfo(pitch.dtype).eps
    up, down = n_ab <= eps * n_cd, n_cd <= eps * n_ab
    half_sum = jnp.arctan2(b, jnp.where(zero_ab, 1.0, a))
    half_diff = jnp.arctan2(d, jnp.where(zero_cd, 1.0, c))
    half_sum = jnp.where(up, -half_diff, half_sum)
    half_diff = jnp.where(down, -half_sum, half_diff)
    return jnp.stack([_wrap(half_sum - half_diff), pitch, _wrap(half_sum + half_diff)], -1)


def _wrap(t: Array) -> Array:
    """An angle in [−2π, 2π] → [−π, π]."""
    return jnp.where(t > jnp.pi, t - 2 * jnp.pi, jnp.where(t < -jnp.pi, t + 2 * jnp.pi, t))


def wxyz_to_xyzw(q: Array) -> Array:
    """Reorder quaternions (…, 4) from scalar-first ``[w, x, y, z]`` to ``[x, y, z, w]``."""
    return jnp.concatenate([q[..., 1:], q[..., :1]], -1)


def xyzw_to_wxyz(q: Array) -> Array:
    """Reorder quaternions (…, 4) from ``[x, y, z, w]`` to scalar-first ``[w, x, y, z]``."""
    return jnp.concatenate([q[..., 3:], q[..., :3]], -1)


def matrix_to_quaternion(m: Array) -> Array:
    """Rotation matrix (…, 3, 3) → quaternion (…, 4), w ≥ 0."""
    return quat.from_matrix(m)


def quaternion_to_matrix(q: Array) -> Array:
    """Quaternion (…, 4) → rotation matrix (…, 3, 3)."""
    return quat.to_matrix(q)


def rotation_vector_to_matrix(phi: Array) -> Array:
    """Axis-angle (…, 3) → rotation matrix (…, 3, 3) (Rodrigues)."""
    return quat.to_matrix(quat.exp(phi))


def matrix_to_rotation_vector(m: Array) -> Array:
    """Rotation matrix (…, 3, 3) → axis-angle (…, 3), angle in [0, π]."""
    return quat.log(quat.from_matrix(m))
