"""Argument checks shared across jaxpose (internal): one place for the messages.

Every check raises an exception naming the argument (``name``) and what was expected.
Shape and type checks only; value checks that must also run under ``jit`` live with
their callers (``equinox.error_if``).
"""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array


def require(name: str, cond: bool, msg: str) -> None:
    """Raise ``ValueError("{name}: {msg}")`` unless ``cond`` (constructor arguments)."""
    if not cond:
        raise ValueError(f"{name}: {msg}")


def check_count(value: Any, name: str, minimum: int = 1) -> int:
    """``value`` as a Python int, refusing anything but a Python or NumPy integer ``>=
    minimum`` (a bool is not a count): TypeError for another type, ValueError below
    ``minimum``; both say "{name}: expected an int >= {minimum}, got ...". Counts that set
    array shapes or loop lengths are static, so this runs on concrete values only."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name}: expected an int >= {minimum}, got {type(value).__name__} "
                        f"{value!r}")
    if value < minimum:
        raise ValueError(f"{name}: expected an int >= {minimum}, got {value!r}")
    return int(value)


def _count_or_none(value: Any, name: str, minimum: int, optional: bool) -> int | None:
    return None if (optional and value is None) else check_count(value, name, minimum)


def count_field(name: str, minimum: int = 1, *, optional: bool = False, **kwargs: Any) -> Any:
    """A static ``equinox`` field holding a count: :func:`check_count` converts it at
    construction (a NumPy integer is stored as an int, not as an array-valued static
    field), ``optional``: None passes. ``kwargs`` go to ``eqx.field`` (``default``)."""
    convert = functools.partial(_count_or_none, name=name, minimum=minimum, optional=optional)
    return eqx.field(static=True, converter=convert, **kwargs)


def as_float_array(x: Any, name: str, what: str = "an array of numbers") -> Array:
    """``x`` as a real floating JAX array (integers promoted to the default float).

    Raises TypeError ("{name}: expected {what}, got ...") for None, strings, mappings,
    sets, complex arrays and anything ``jnp.asarray`` rejects."""
    if x is None or isinstance(x, (str, bytes, dict, set)):
        raise TypeError(f"{name}: expected {what}, got {type(x).__name__}")
    try:
        arr = jnp.asarray(x)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name}: expected {what}, got {type(x).__name__}") from err
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        if jnp.issubdtype(arr.dtype, jnp.complexfloating):
            raise TypeError(f"{name}: expected a real floating array, got {arr.dtype}")
        arr = arr.astype(jnp.result_type(float))
    return arr


def numpy_field(value: Any, dtype: Any, shape: tuple[int | None, ...], name: str) -> np.ndarray:
    """``value`` as a NumPy array of ``dtype`` whose shape matches ``shape`` (None: any size).

    With ``dtype=np.int64``, non-integer input is refused rather than truncated; a traced
    array (inside ``jit``/``grad``/``vmap``) is refused with the way to differentiate."""
    if isinstance(getattr(value, "data", value), jax.core.Tracer):
        raise TypeError(
            f"{name}: got a traced array (inside jax.jit, grad or vmap); this container "
            f"holds NumPy data (as read from a file) and is built outside traced code. To "
            f"differentiate through a solve, build the factor graph outside "
            f"(jaxpose.graph.pose_graph_problem / bundle_adjustment_problem) and replace its "
            f"factor data inside the traced function, e.g. "
            f"eqx.tree_at(lambda g: g.factors[0].data, graph, new_data) (docs/graph.md, "
            f"'Differentiating through a solution')")
    arr = np.asarray(value)
    if dtype is np.int64 and arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name}: expected integers, got dtype {arr.dtype}")
    arr = np.asarray(arr, dtype=dtype)
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {arr.shape}")
    return arr


def set_numpy_field(
    obj: Any, name: str, dtype: Any, shape: tuple[int | None, ...], *, unwrap: bool = False
) -> None:
    """Replace the field ``obj.name`` of a frozen dataclass by its checked NumPy form
    (:func:`numpy_field`, errors naming ``Class.name``). ``unwrap``: take ``value.data``
    when present (jaxpose groups)."""
    value = getattr(obj, name)
    if unwrap:
        value = getattr(value, "data", value)
    arr = numpy_field(value, dtype, shape, f"{type(obj).__name__}.{name}")
    object.__setattr__(obj, name, arr)
