"""Absolute time stamps as arrays that keep their differences (internal).

Time stamps are used by their differences only (association, spline knots), but arrive
as absolute values: epoch seconds (1.6e9, float32 spacing 128 s) or nanoseconds. Cast to
float32 (JAX's default, or a float32 problem's dtype) they collapse onto a coarse grid
before anything is subtracted. :func:`shifted` subtracts a common origin on the host,
where the values are still exact.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np


def shifted(*stamps: Any) -> tuple[Any, ...]:
    """``stamps`` minus one common origin (the first value of the first sequence) as
    float64 NumPy arrays, when every sequence is host data (NumPy arrays, lists, scalars)
    of integers or floats; otherwise (a JAX array, traced or not, whose precision is the
    caller's; or anything the callers' own checks refuse) unchanged. Integer stamps are
    subtracted exactly in int64 first (nanoseconds: exact differences up to 2⁵³ ns, 104
    days), and returned as floats: with x64 off JAX would wrap int64 differences beyond
    2³¹ (2.1 s in nanoseconds) into int32. Differences, and so every result computed from
    them, stay the same; the values become small enough for float32."""
    if any(isinstance(s, jax.Array) or s is None for s in stamps):
        return stamps
    try:
        arrays = [np.asarray(s) for s in stamps]
    except (TypeError, ValueError):
        return stamps
    if not all(a.dtype.kind in "iuf" and a.size for a in arrays):
        return stamps
    origin = arrays[0].reshape(-1)[0]
    if all(a.dtype.kind in "iu" for a in arrays):
        return tuple((a.astype(np.int64) - np.int64(origin)).astype(np.float64)
                     for a in arrays)
    return tuple(a.astype(np.float64) - np.float64(origin) for a in arrays)
