"""Test helpers: :func:`assert_close`, a Lie-aware ``numpy.testing.assert_allclose``.

Group elements are close when ``Log(desired⁻¹·actual)`` is close to zero (so q and −q,
and any two storages of one element, compare equal), as PyPose's
``pp.testing.assert_close``; algebra elements and arrays compare elementwise. Pytrees
(dicts, lists, equinox modules) are compared leaf by leaf, the failing path is named.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .lie._base import LieAlgebra, LieGroup

_DEFAULT_TOL = {  # (rtol, atol) by dtype, as torch.testing.assert_close
    np.dtype(np.float16): (1e-3, 1e-5),
    np.dtype(np.float32): (1.3e-6, 1e-5),
    np.dtype(np.float64): (1e-7, 1e-7),
}


def _is_lie(x: Any) -> bool:
    return isinstance(x, LieGroup | LieAlgebra)


def assert_close(actual: Any, desired: Any, *, rtol: float | None = None,
                 atol: float | None = None) -> None:
    """Raise ``AssertionError`` unless ``actual`` and ``desired`` (arrays, Lie elements or
    pytrees of them, same structure and types) agree to ``|a − d| ≤ atol + rtol·|d|``.

    Default tolerances follow the dtype (float32: rtol 1.3e-6, atol 1e-5; float64: 1e-7);
    give both or neither. Groups: ``Log(desired⁻¹·actual)`` against zero (atol only)."""
    if (rtol is None) != (atol is None):
        raise ValueError("assert_close(rtol, atol): give both or neither")
    a_leaves, a_def = jax.tree_util.tree_flatten_with_path(actual, is_leaf=_is_lie)
    d_leaves, d_def = jax.tree_util.tree_flatten_with_path(desired, is_leaf=_is_lie)
    if a_def != d_def:
        raise AssertionError(f"assert_close: different structures:\n  actual:  {a_def}\n"
                             f"  desired: {d_def}")
    for (path, a), (_, d) in zip(a_leaves, d_leaves, strict=True):
        where = jax.tree_util.keystr(path) or "value"
        if _is_lie(a) or _is_lie(d):
            if type(a) is not type(d):
                raise AssertionError(f"assert_close at {where}: types differ, "
                                     f"{type(a).__name__} vs {type(d).__name__}")
            if isinstance(a, LieGroup):
                a, d = np.asarray(d.inv().compose(a).log().data), None
            else:
                a, d = np.asarray(a.data), np.asarray(d.data)
        else:
            a, d = np.asarray(a), np.asarray(d)
        dtype = np.result_type(a, d) if d is not None else a.dtype
        r, t = (rtol, atol) if rtol is not None else _DEFAULT_TOL.get(
            np.dtype(dtype) if jnp.issubdtype(dtype, jnp.floating) else None, (0.0, 0.0))
        if d is None:  # group: tangent distance against zero
            d, r = np.zeros_like(a), 0.0
        np.testing.assert_allclose(a, d, rtol=r, atol=t, err_msg=f"assert_close at {where}")


__all__ = ["assert_close"]
