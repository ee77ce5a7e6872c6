"""Shared helpers for :mod:`jaxpose.geometry`: argument checks and safe math.

Checks run at trace time on shapes and types and raise exceptions that name the argument;
conditions that depend on values (degenerate configurations, non-finite data) are
reported through :class:`~jaxpose.Results` codes in the results instead.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..lie._base import LieGroup, as_float_array

Array = jax.Array


def points_array(x: Any, argname: str, dim: int | None = 3, min_points: int = 1) -> Array:
    """``x`` as a float array of shape (..., N, dim) with N ≥ ``min_points``."""
    arr = as_float_array(x, argname)
    want = "D" if dim is None else str(dim)
    if arr.ndim < 2 or (dim is not None and arr.shape[-1] != dim):
        raise ValueError(f"{argname}: expected an array of shape (..., N, {want}), "
                         f"got shape {tuple(arr.shape)}")
    n = arr.shape[-2]
    if n < min_points:
        what = "an empty point set" if n == 0 else f"{n} point{'s' if n != 1 else ''}"
        raise ValueError(f"{argname}: expected at least {min_points} point"
                         f"{'s' if min_points != 1 else ''}, got {what} "
                         f"(shape {tuple(arr.shape)})")
    return arr


def matrix_array(x: Any, argname: str, n: int, m: int | None = None) -> Array:
    """``x`` as a float array of shape (..., n, m)."""
    m = n if m is None else m
    arr = as_float_array(x, argname)
    if arr.ndim < 2 or arr.shape[-2:] != (n, m):
        raise ValueError(f"{argname}: expected an array of shape (..., {n}, {m}), "
                         f"got shape {tuple(arr.shape)}")
    return arr


def check_group(x: Any, cls: type[LieGroup], argname: str) -> LieGroup:
    if not isinstance(x, cls):
        hint = f"; wrap a raw array as {cls.__name__}(array)" if isinstance(
            x, (jax.Array, np.ndarray)) else ""
        raise TypeError(f"{argname}: expected a {cls.__name__} element, got "
                        f"{type(x).__name__}{hint}")
    return x


def batch_shape(*shapes: tuple[int, ...], names: tuple[str, ...]) -> tuple[int, ...]:
    """Broadcast batch shapes, naming the arguments when they do not broadcast."""
    try:
        return tuple(np.broadcast_shapes(*shapes))
    except ValueError as err:
        desc = ", ".join(f"{n} {tuple(s)}" for n, s in zip(names, shapes))
        raise ValueError(f"batch shapes do not broadcast: {desc}") from err


def same_count(a: Array, b: Array, name_a: str, name_b: str, axis: int = -2) -> None:
    if a.shape[axis] != b.shape[axis]:
        raise ValueError(f"{name_a} and {name_b}: expected the same number of points, got "
                         f"{a.shape[axis]} and {b.shape[axis]} (shapes {tuple(a.shape)} and "
                         f"{tuple(b.shape)})")


def common_dtype(*xs: Array) -> Any:
    return jnp.result_type(*[x.dtype for x in xs])


def flatten_batch(x: Array, batch: tuple[int, ...], core_ndim: int) -> Array:
    """Broadcast ``x`` to ``(*batch, *core)`` and merge the batch axes into one."""
    core = x.shape[x.ndim - core_ndim:] if core_ndim else ()
    return jnp.broadcast_to(x, (*batch, *core)).reshape((-1, *core))


def exp_act2(delta: Array, p: Array) -> Array:
    """Exp(δ)·p to second order in δ = [ρ, φ] (se3 layout), for points p (..., 3):
    p + ρ + φ×p + ½ φ×(φ×p + ρ). Its value, first and second derivatives at δ = 0 are
    those of the SE3 action, so Hessians of a cost at δ = 0 built on it are exact — and
    far cheaper to compile than differentiating the series branches of SE3.exp twice."""
    rho, phi = delta[..., :3], delta[..., 3:]
    first = rho + jnp.cross(phi, p)
    return p + first + 0.5 * jnp.cross(phi, first)


def spd_solve(a: Array, b: Array) -> Array:
    """x = a⁻¹ b for a small symmetric positive-definite ``a`` (n, n) and ``b`` (n,), by a
    Cholesky factorisation unrolled over the static size n (elementwise code, so a vmap
    over many small systems vectorises instead of calling LAPACK once per system).
    Meant for n ≲ 8; a non-positive pivot gives NaN (callers damp ``a``)."""
    n = a.shape[-1]
    low = [[None] * n for _ in range(n)]
    for j in range(n):
        d = a[j, j] - sum(low[j][k] * low[j][k] for k in range(j))
        low[j][j] = jnp.sqrt(d)
        for i in range(j + 1, n):
            low[i][j] = (a[i, j] - sum(low[i][k] * low[j][k] for k in range(j))) / low[j][j]
    y = [None] * n
    for i in range(n):  # L y = b
        y[i] = (b[i] - sum(low[i][k] * y[k] for k in range(i))) / low[i][i]
    x = [None] * n
    for i in reversed(range(n)):  # Lᵀ x = y
        x[i] = (y[i] - sum(low[k][i] * x[k] for k in range(i + 1, n))) / low[i][i]
    return jnp.stack(x)
