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
    """Quaternion (…, 4) → roll-pitch-yaw (…, 3); pitch in [−π/2, π/2] (gimbal lock at ±π/2,
    where the derivative of pitch is unbounded)."""
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    roll = jnp.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = jnp.arcsin(jnp.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return jnp.stack([roll, pitch, yaw], -1)


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
