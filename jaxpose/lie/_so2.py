"""SO(2): planar rotations stored as ``[cos θ, sin θ]``; algebra so2 = ``[θ]``."""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp

from ._base import Array, LieAlgebra, LieGroup, parts


class so2(LieAlgebra):  # noqa: N801
    """so(2) element: ``data`` (..., 1) = ``[θ]``."""

    tangent_dim: ClassVar[int] = 1
    layout: ClassVar[str] = "[θ]"


def rot2(cs: Array) -> Array:
    """2×2 rotation matrices (..., 2, 2) from ``[cos, sin]`` (..., 2)."""
    c, s = parts(cs)
    return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)


def rotated(c: Array, s: Array, x: Array, y: Array) -> tuple[Array, Array]:
    """(x, y) rotated by the angle of cosine ``c`` and sine ``s``, by components (the
    kernels take components with :func:`~jaxpose.lie._base.parts`, not slices)."""
    return c * x - s * y, s * x + c * y


def rotate2(cs: Array, p: Array) -> Array:
    """``p`` (…, 2) rotated by ``[cos, sin]`` (…, 2)."""
    return jnp.stack(rotated(*parts(cs), *parts(p)), -1)


def mul2(a: Array, b: Array) -> Array:
    """Complex product of unit complex numbers ``[cos, sin]`` (``b`` rotated by ``a``)."""
    return jnp.stack(rotated(*parts(a), *parts(b)), -1)


def conj2(a: Array) -> Array:
    c, s = parts(a)
    return jnp.stack([c, -s], -1)


def angle(cs: Array) -> Array:
    """θ ∈ (−π, π] from ``[cos, sin]`` (…, 2) → (…,)."""
    c, s = parts(cs)
    return jnp.arctan2(s, c)


def normalize2(cs: Array) -> Array:
    """``[cos, sin]`` (…, 2) divided by its norm, without overflow or underflow (the pair
    is first divided by its larger magnitude, held constant in derivatives, which the
    scale does not change: through 1/m they were NaN below ×1e-160); ``[0, 0]`` gives NaN."""
    c, s = parts(cs)
    m = jax.lax.stop_gradient(jnp.maximum(jnp.abs(c), jnp.abs(s)))
    scale = 1.0 / jnp.where(m > 0, m, 1.0)
    c, s = c * scale, s * scale
    n = jnp.sqrt(c * c + s * s)
    return jnp.stack([c / n, s / n], -1)


class SO2(LieGroup):
    """SO(2) element: ``data`` (..., 2) = ``[cos θ, sin θ]``."""

    storage_dim: ClassVar[int] = 2
    tangent_dim: ClassVar[int] = 1
    matrix_dim: ClassVar[int] = 2
    point_dim: ClassVar[int] = 2
    layout: ClassVar[str] = "[cos θ, sin θ]"
    algebra: ClassVar[type[LieAlgebra]] = so2
    unit_slice: ClassVar[tuple[int, int]] = (0, 2)

    @staticmethod
    def _identity_data() -> Array:
        return jnp.array([1.0, 0.0])

    @staticmethod
    def _exp(a: Array) -> Array:
        return jnp.concatenate([jnp.cos(a), jnp.sin(a)], -1)

    @staticmethod
    def _exp_linear(a: Array) -> Array:
        return jnp.concatenate([jnp.ones_like(a), a], -1)

    @staticmethod
    def _exp_quadratic(a: Array) -> Array:
        return jnp.concatenate([1.0 - 0.5 * a * a, a], -1)

    @staticmethod
    def _log(x: Array) -> Array:
        return angle(x)[..., None]

    _compose = staticmethod(mul2)
    _inv = staticmethod(conj2)
    _act = staticmethod(rotate2)
    _matrix = staticmethod(rot2)
    _normalize = staticmethod(normalize2)

    @staticmethod
    def _from_matrix(m: Array) -> Array:
        # Projection onto SO(2): the angle of the rotation closest to m.
        # A reflection has c = s = 0 (every rotation is equally close): the identity is
        # returned there, so the result is always a valid element (double-where, NaN-free).
        c = m[..., 0, 0] + m[..., 1, 1]
        s = m[..., 1, 0] - m[..., 0, 1]
        big = jnp.maximum(jnp.abs(c), jnp.abs(s))  # rescale: no overflow/underflow of n2
        big = jnp.where(big > 0, big, 1.0)
        c, s = c / big, s / big
        n2 = c * c + s * s
        ok = n2 > jnp.finfo(m.dtype).tiny
        inv = 1.0 / jnp.sqrt(jnp.where(ok, n2, 1.0))
        return jnp.stack([jnp.where(ok, c * inv, 1.0), jnp.where(ok, s * inv, 0.0)], -1)

    @staticmethod
    def _adj_matrix(x: Array) -> Array:
        return jnp.ones((*x.shape[:-1], 1, 1), x.dtype)

    @staticmethod
    def _jl(a: Array) -> Array:
        return jnp.ones((*a.shape[:-1], 1, 1), a.dtype)

    @staticmethod
    def _jl_inv(a: Array) -> Array:
        return jnp.ones((*a.shape[:-1], 1, 1), a.dtype)

    @staticmethod
    def _hat(a: Array) -> Array:
        z = jnp.zeros_like(a[..., 0])
        t = a[..., 0]
        return jnp.stack([jnp.stack([z, -t], -1), jnp.stack([t, z], -1)], -2)

    def rotation(self) -> SO2:
        """The element itself (it is a rotation)."""
        return self

    def angle(self) -> Array:
        """Rotation angle θ ∈ (−π, π] (…,)."""
        return angle(self.data)


so2.group = SO2
