"""The dtype policy of jaxpose's loops (internal).

A loop's state keeps the dtype of its start: a float32 state stepped with float64 data
(NumPy arrays with x64 on) is computed in float64 by JAX's promotion and rounded back
each step, instead of failing with a ``lax.scan``/``while_loop`` carry type error.
"""

from __future__ import annotations

from typing import Any

import jax


def keep_dtypes(new: Any, old: Any) -> Any:
    """``new`` with every array leaf cast to the dtype of the matching leaf of ``old``
    (same pytree structure: a loop's next state and its current one)."""
    return jax.tree.map(lambda n, o: n.astype(o.dtype), new, old)

