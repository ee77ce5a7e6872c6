"""RxSO(3): rotation and positive scale, stored as ``[qx, qy, qz, qw, s]`` (PyPose order).

Algebra rxso3: ``[φx, φy, φz, σ]`` with s = e^σ. The group is the direct product
SO(3) × R⁺, so its Jacobians are block-diagonal.
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp

from . import _quaternion as quat
from ._base import Array, LieAlgebra, LieGroup, skew
from ._so3 import SO3


class rxso3(LieAlgebra):  # noqa: N801
    """rxso(3) element: ``data`` (..., 4) = ``[φx, φy, φz, σ]``."""

    tangent_dim: ClassVar[int] = 4
    layout: ClassVar[str] = "[φx, φy, φz, σ]"


def _block_diag_1(m: Array) -> Array:
    """[[m, 0], [0, 1]] for m (..., 3, 3)."""
    z = jnp.zeros((*m.shape[:-2], 3, 1), m.dtype)
    top = jnp.concatenate([m, z], -1)
    one = jnp.ones((*m.shape[:-2], 1, 1), m.dtype)
    bottom = jnp.concatenate([jnp.swapaxes(z, -1, -2), one], -1)
    return jnp.concatenate([top, bottom], -2)


def cbrt_det(m: Array) -> Array:
    """Scale s = |det M|^(1/3) of a scaled rotation M = sR (…, 3, 3) → (…,).

    The absolute value keeps s > 0 for an improper M (a reflection), which then fails the
    ``from_matrix`` check instead of producing an element with a negative scale. The
    determinant is taken of M / max |Mᵢⱼ| (then rescaled), so scales of 1e±200 neither
    overflow nor underflow."""
    big = jnp.max(jnp.abs(m), axis=(-2, -1))
    big = jnp.where(big > 0, big, 1.0)
    return big * jnp.cbrt(jnp.abs(jnp.linalg.det(m / big[..., None, None])))


class RxSO3(LieGroup):
    """RxSO(3) element: ``data`` (..., 5) = ``[qx, qy, qz, qw, s]`` with s > 0."""

    storage_dim: ClassVar[int] = 5
    tangent_dim: ClassVar[int] = 4
    matrix_dim: ClassVar[int] = 3
    point_dim: ClassVar[int] = 3
    layout: ClassVar[str] = "[qx, qy, qz, qw, s]"
    algebra: ClassVar[type[LieAlgebra]] = rxso3
    unit_slice: ClassVar[tuple[int, int]] = (0, 4)
    scale_index: ClassVar[int | None] = 4

    @staticmethod
    def _identity_data() -> Array:
        return jnp.array([0.0, 0.0, 0.0, 1.0, 1.0])

    @staticmethod
    def _exp(a: Array) -> Array:
        return jnp.concatenate([quat.exp(a[..., :3]), jnp.exp(a[..., 3:])], -1)

    @staticmethod
    def _exp_linear(a: Array) -> Array:
        one = jnp.ones_like(a[..., :1])
        return jnp.concatenate([0.5 * a[..., :3], one, one + a[..., 3:]], -1)

    @staticmethod
    def _exp_quadratic(a: Array) -> Array:
        phi, sigma = a[..., :3], a[..., 3:]
        w = 1.0 - 0.125 * jnp.sum(phi * phi, -1, keepdims=True)
        return jnp.concatenate([0.5 * phi, w, 1.0 + sigma + 0.5 * sigma * sigma], -1)

    @staticmethod
    def _log(x: Array) -> Array:
        return jnp.concatenate([quat.log(x[..., :4]), jnp.log(x[..., 4:])], -1)

    @staticmethod
    def _compose(a: Array, b: Array) -> Array:
        return jnp.concatenate([quat.multiply(a[..., :4], b[..., :4]), a[..., 4:] * b[..., 4:]], -1)

    @staticmethod
    def _inv(x: Array) -> Array:
        return jnp.concatenate([quat.conjugate(x[..., :4]), 1.0 / x[..., 4:]], -1)

    @staticmethod
    def _act(x: Array, p: Array) -> Array:
        return x[..., 4:] * quat.rotate(x[..., :4], p)

    @staticmethod
    def _matrix(x: Array) -> Array:
        return x[..., 4:, None] * quat.to_matrix(x[..., :4])

    @staticmethod
    def _from_matrix(m: Array) -> Array:
        s = cbrt_det(m)
        return jnp.concatenate([quat.from_matrix(m / s[..., None, None]), s[..., None]], -1)

    @staticmethod
    def _adj_matrix(x: Array) -> Array:
        return _block_diag_1(quat.to_matrix(x[..., :4]))

    @staticmethod
    def _jl(a: Array) -> Array:
        return _block_diag_1(quat.jl(a[..., :3]))

    @staticmethod
    def _jl_inv(a: Array) -> Array:
        return _block_diag_1(quat.jl_inv(a[..., :3]))

    @staticmethod
    def _hat(a: Array) -> Array:
        return skew(a[..., :3]) + a[..., 3:, None] * jnp.eye(3, dtype=a.dtype)

    @staticmethod
    def _normalize(x: Array) -> Array:
        return jnp.concatenate([quat.normalize(x[..., :4]), x[..., 4:]], -1)

    def rotation(self) -> SO3:
        """Rotation part as SO3 (data (…, 4) = ``[qx, qy, qz, qw]``)."""
        return SO3(self.data[..., :4])

    def scale(self) -> Array:
        """Scale s (…,)."""
        return self.data[..., 4]

    def euler(self) -> Array:
        """Roll-pitch-yaw ``[r, p, y]`` (…, 3) of the rotation part."""
        return self.rotation().euler()


rxso3.group = RxSO3
