"""SO(3): 3D rotations stored as unit quaternions ``[qx, qy, qz, qw]`` (PyPose order).

Algebra so3: rotation vector ``[φx, φy, φz]`` (axis × angle, angle in [0, π] from log).
"""

from __future__ import annotations

from typing import Any, ClassVar

import jax.numpy as jnp

from . import _quaternion as quat
from ._base import Array, LieAlgebra, LieGroup, as_float_array, check_last_dim, skew


class so3(LieAlgebra):  # noqa: N801 - algebra names are lower-case, as in PyPose
    """so(3) element: ``data`` (..., 3) = rotation vector φ."""

    tangent_dim: ClassVar[int] = 3
    layout: ClassVar[str] = "[φx, φy, φz]"


class SO3(LieGroup):
    """SO(3) element: ``data`` (..., 4) = unit quaternion ``[qx, qy, qz, qw]``."""

    storage_dim: ClassVar[int] = 4
    tangent_dim: ClassVar[int] = 3
    matrix_dim: ClassVar[int] = 3
    point_dim: ClassVar[int] = 3
    layout: ClassVar[str] = "[qx, qy, qz, qw]"
    algebra: ClassVar[type[LieAlgebra]] = so3
    unit_slice: ClassVar[tuple[int, int]] = (0, 4)

    # -- raw array functions -----------------------------------------------------------
    @staticmethod
    def _identity_data() -> Array:
        return jnp.array([0.0, 0.0, 0.0, 1.0])

    _exp = staticmethod(quat.exp)

    @staticmethod
    def _exp_linear(phi: Array) -> Array:
        return jnp.concatenate([0.5 * phi, jnp.ones_like(phi[..., :1])], -1)

    @staticmethod
    def _exp_quadratic(phi: Array) -> Array:
        w = 1.0 - 0.125 * jnp.sum(phi * phi, -1, keepdims=True)
        return jnp.concatenate([0.5 * phi, w], -1)

    _log = staticmethod(quat.log)
    _compose = staticmethod(quat.multiply)
    _inv = staticmethod(quat.conjugate)
    _act = staticmethod(quat.rotate)
    _matrix = staticmethod(quat.to_matrix)
    _from_matrix = staticmethod(quat.from_matrix)
    _adj_matrix = staticmethod(quat.to_matrix)
    _jl = staticmethod(quat.jl)
    _jl_inv = staticmethod(quat.jl_inv)

    @staticmethod
    def _jl_inv_principal(phi: Array) -> Array:
        return quat.jl_inv(phi, principal=True)

    _hat = staticmethod(skew)
    _normalize = staticmethod(quat.normalize)

    # -- components --------------------------------------------------------------------
    def rotation(self) -> SO3:
        """The element itself (it is a rotation)."""
        return self

    def euler(self) -> Array:
        """Roll-pitch-yaw ``[r, p, y]`` (…, 3) with R = Rz(y)·Ry(p)·Rx(r)."""
        from .convert import quaternion_to_euler

        return quaternion_to_euler(self.data)

    @classmethod
    def from_euler(cls, euler: Any) -> SO3:
        """From roll-pitch-yaw ``[r, p, y]`` (…, 3), R = Rz(y)·Ry(p)·Rx(r)."""
        from .convert import euler_to_quaternion

        e = as_float_array(euler, "SO3.from_euler(euler)")
        check_last_dim(e, 3, "SO3.from_euler(euler)", "[roll, pitch, yaw]")
        return cls(euler_to_quaternion(e))

    def wxyz(self) -> Array:
        """Quaternion in scalar-first order ``[qw, qx, qy, qz]`` (…, 4)."""
        return jnp.concatenate([self.data[..., 3:], self.data[..., :3]], -1)

    @classmethod
    def from_wxyz(cls, q: Any, check: bool = False) -> SO3:
        """From a scalar-first quaternion ``[qw, qx, qy, qz]`` (…, 4); ``check`` as in
        ``SO3(data, check=True)``."""
        arr = as_float_array(q, "SO3.from_wxyz(q)")
        check_last_dim(arr, 4, "SO3.from_wxyz(q)", "[qw, qx, qy, qz]")
        return cls(jnp.concatenate([arr[..., 1:], arr[..., :1]], -1), check=check)

    @classmethod
    def from_xyzw(cls, q: Any, check: bool = False) -> SO3:
        """From a scalar-last quaternion (the storage order itself); ``check`` as in
        ``SO3(data, check=True)``."""
        return cls(q, check=check)


so3.group = SO3
