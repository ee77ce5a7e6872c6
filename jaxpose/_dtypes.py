"""The dtype policy of jaxpose's loops (internal): integer starting values become
floats (:func:`inexact`), and a loop's state keeps the dtype of its start
(:func:`keep_dtypes`).

A loop's state keeps the dtype of its start: a float32 state stepped with float64 data
(NumPy arrays with x64 on) is computed in float64 by JAX's promotion and rounded back
each step, instead of failing with a ``lax.scan``/``while_loop`` carry type error.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp


def keep_dtypes(new: Any, old: Any) -> Any:
    """``new`` with every array leaf cast to the dtype of the matching leaf of ``old``
    (same pytree structure: a loop's next state and its current one)."""
    return jax.tree.map(lambda n, o: n.astype(o.dtype), new, old)


def inexact(tree: Any) -> Any:
    """Integer or bool array leaves (and Python numbers) of ``tree`` as floating arrays of
    JAX's default float dtype: the starting values of a continuous optimisation."""

    def leaf(x: Any) -> Any:
        if isinstance(x, bool | int | float) or (
            eqx.is_array_like(x) and not jnp.issubdtype(jnp.result_type(x), jnp.inexact)
        ):
            return jnp.asarray(x, jnp.result_type(float))
        return x

    return jax.tree.map(leaf, tree)
