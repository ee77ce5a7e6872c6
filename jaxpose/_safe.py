"""Elementary functions whose derivatives stay finite where the plain ones are Inf/NaN.

The ``where``-twice pattern: the unsafe branch never sees its singular point, so neither
its value nor any order of its derivative is NaN there (a NaN input stays NaN)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array


def safe_norm(x: Array, axis: int = -1, keepdims: bool = False) -> Array:
    """Euclidean norm whose derivative is 0 (not NaN) at x = 0, any order (NaN stays NaN)."""
    sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), sq)


def safe_sqrt(x: Array) -> Array:
    """sqrt(max(x, 0)) with derivative 0 (not Inf/NaN) at x ≤ 0 (NaN stays NaN)."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), jnp.where(x == x, 0.0, x))


def safe_div(num: Array, den: Array) -> Array:
    """num / den, with den = 0 replaced by 1 (result 0·num) so derivatives stay finite."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


__all__ = ["safe_div", "safe_norm", "safe_sqrt"]
