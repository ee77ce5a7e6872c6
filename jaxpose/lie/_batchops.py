"""PyPose's batch helpers: ``identity_like``, ``random_like`` (``randn_like``) and
``cumops`` (a cumulative scan with any associative operation).

Groups and algebras alike: the result has the input's type, batch shape and dtype.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import jax
import jax.numpy as jnp

from ._base import LieAlgebra, LieGroup

T = TypeVar("T", LieGroup, LieAlgebra)


def _lie(x: Any, fn: str) -> LieGroup | LieAlgebra:
    if not isinstance(x, LieGroup | LieAlgebra):
        raise TypeError(f"{fn}(x): expected a Lie group or algebra element, got "
                        f"{type(x).__name__}")
    return x


def identity_like(x: T) -> T:
    """The identity of ``x``'s type (zero tangent vector for an algebra), same batch shape
    and dtype (PyPose's ``identity_like``)."""
    x = _lie(x, "identity_like")
    if isinstance(x, LieGroup):
        return type(x).identity(x.shape, x.dtype)
    return type(x)(jnp.zeros_like(x.data))


def random_like(x: T, key: Any, sigma: Any = 1.0) -> T:
    """Random elements of ``x``'s type, batch shape and dtype (PyPose's ``randn_like``):
    ``Exp(σ·n)`` for a group, ``σ·n`` for an algebra, n ~ N(0, I) in the tangent space
    (explicit PRNG ``key``); ``sigma`` one std or one per tangent coordinate, as in
    ``SE3.random`` and the other groups' ``random``."""
    x = _lie(x, "random_like")
    if isinstance(x, LieGroup):
        return type(x).random(key, x.shape, sigma, x.dtype)
    if not isinstance(key, jax.Array):
        raise TypeError(f"random_like(key): expected a jax.random key, got {key!r}")
    n = jax.random.normal(key, x.data.shape, x.dtype)
    return type(x)(jnp.asarray(sigma, x.dtype) * n)


def cumops(x: T, op: Callable[[T, T], T], axis: int = 0) -> T:
    """Cumulative ``op`` along a batch ``axis``: Yᵢ = X₀ ∘ X₁ ∘ … ∘ Xᵢ (PyPose's
    ``cumops``), in O(log N) depth with ``jax.lax.associative_scan``.

    ``op(a, b)`` takes and returns elements of ``x``'s type and must be associative
    (``lambda a, b: a @ b`` is ``x.cumprod(axis, left=False)``; ``lambda a, b: b @ a``
    is ``x.cumprod(axis)``); it is called on batches of elements."""
    x = _lie(x, "cumops")
    if not callable(op):
        raise TypeError(f"cumops(op): expected a callable op(a, b), got {op!r}")
    nb = len(x.shape)
    if not isinstance(axis, int) or not -nb <= axis < max(nb, 1) or nb == 0:
        raise ValueError(f"cumops(axis={axis!r}): expected a batch axis of shape {x.shape}")
    cls = type(x)

    def data_op(a: Any, b: Any) -> Any:
        out = op(cls(a), cls(b))
        if type(out) is not cls:
            raise TypeError(f"cumops(op): op returned {type(out).__name__}, expected "
                            f"{cls.__name__}")
        return out.data

    return cls(jax.lax.associative_scan(data_op, x.data, axis=axis % nb))


__all__ = ["cumops", "identity_like", "random_like"]
