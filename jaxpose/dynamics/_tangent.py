"""Flat tangent-space views of states that are arrays, Lie groups or pytrees of both.

Filters and linearisation work with flat vectors: ``plus(x, d)`` is ``x ⊕ d`` (``x + d``
for arrays, ``X·Exp(d)`` for groups, see :mod:`jaxpose.lie.manifold`) and
``minus(a, b)`` is ``a ⊖ b`` flattened to one vector.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from ..lie import manifold
from ..lie._base import LieAlgebra, LieGroup

Array = jax.Array


class TangentSpace(NamedTuple):
    """``dim`` flat tangent coordinates; ``plus``/``minus`` the retraction and its inverse."""

    dim: int
    plus: Callable[[Any, Array], Any]
    minus: Callable[[Any, Any], Array]
    euclidean: bool


def is_euclidean(x: Any) -> bool:
    """True when ``x`` is a plain array (no group leaves)."""
    return not any(
        isinstance(leaf, LieGroup)
        for leaf in jax.tree.leaves(x, is_leaf=lambda v: isinstance(v, LieGroup))
    )


def tangent_space(x: Any) -> TangentSpace:
    """Tangent-space operations for one (unbatched) state ``x``."""
    # Lie elements define __array__ (np.asarray(X) is X.data) but are pytrees, not arrays
    if not isinstance(x, LieGroup | LieAlgebra) and (
        isinstance(x, (jax.Array, float, int)) or hasattr(x, "__array__")
    ):
        arr = jnp.asarray(x)
        if arr.ndim != 1:
            raise ValueError(f"state: expected a vector of shape (n,), got {tuple(arr.shape)}")
        return TangentSpace(int(arr.shape[0]), lambda a, d: a + d, lambda a, b: a - b, True)
    flat, unravel = manifold.flat_tangent(x)

    def plus(a: Any, d: Array) -> Any:
        return manifold.retract(a, unravel(d))

    def minus(a: Any, b: Any) -> Array:
        return ravel_pytree(manifold.rminus(a, b))[0]

    return TangentSpace(int(flat.shape[0]), plus, minus, is_euclidean(x))


def tangent_jacobian(
    fn: Callable[[Any], Any], x: Any, ts_in: TangentSpace, ts_out: TangentSpace | None = None
) -> tuple[Any, Array]:
    """``(fn(x), J)`` with ``J = d[fn(x ⊕ δ) ⊖ fn(x)]/dδ`` at δ = 0 (forward mode)."""
    y = fn(x)
    ts_out = ts_out or tangent_space(y)

    def local(d: Array) -> Array:
        return ts_out.minus(fn(ts_in.plus(x, d)), y)

    J = jax.jacfwd(local)(jnp.zeros(ts_in.dim, dtype=_dtype(x)))
    return y, J


def _dtype(x: Any) -> Any:
    leaves = jax.tree.leaves(x)
    return jnp.result_type(*leaves) if leaves else jnp.result_type(float)
