"""Batched Cholesky factorisations and linear solves of small matrices, written out in
elementwise operations instead of LAPACK calls.

On the CPU, ``jnp.linalg.cholesky``, ``solve`` and ``inv`` are LAPACK custom calls.
jaxlib 0.10.2 splits a large batch of them over XLA's intra-op thread pool and blocks a
pool thread until the pieces finish; when a program runs as many such calls at once as
the pool has threads (two on a 2-core machine, a Colab runtime or CI), every thread
waits and the program never finishes: no error, no CPU use. jaxpose's per-factor and
per-variable blocks (information matrices, block-Jacobi and Schur blocks, the
similarity log's 3×3 solve, IMU windows' information) are batched over a whole graph,
large enough to take that path. Written out — Cholesky factors and inverses of
symmetric positive-definite matrices up to d = :data:`UNROLL_MAX`, general inverses and
solves up to d = 3 (the adjugate) — they contain no custom call, and XLA fuses them
into loops over the batch: on the CPU as fast as the per-matrix LAPACK calls or faster
(6275 6×6 Cholesky factors 1x, 2500 9×9 inverses 1.7x, 2000 3×3 inverses 10x). Larger
matrices keep ``jnp.linalg``.

Every function is a composition of differentiable operations: derivatives of any
order, ``jit`` and ``vmap`` as for any JAX code. Batch dimensions lead (``...``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array

UNROLL_MAX = 9
"""Largest symmetric positive-definite d written out (BAL cameras, IMU factors); larger
matrices use ``jnp.linalg`` (LAPACK on the CPU)."""


def _cholesky(a: Array) -> tuple[Array, Array]:
    """(L (..., d, d), ok (...,)): the Cholesky factor of ½(a + aᵀ), column by column
    (left-looking: a few vector operations per column, so the program grows with d, not
    d³); ``ok`` is False where a pivot is not positive (L is then finite but
    meaningless)."""
    d = a.shape[-1]
    sym = 0.5 * (a + jnp.swapaxes(a, -1, -2))
    low = jnp.zeros_like(sym)
    ok = jnp.ones(a.shape[:-2], bool)
    for j in range(d):
        col = sym[..., j:, j] - jnp.sum(low[..., j:, :j] * low[..., j, None, :j], -1)
        pivot = col[..., 0]
        ok = ok & (pivot > 0)
        col = col / jnp.sqrt(jnp.where(pivot > 0, pivot, 1.0))[..., None]
        low = low.at[..., j:, j].set(col)
    return low, ok


def _nan_where_not(ok: Array, x: Array) -> Array:
    return jnp.where(ok[..., None, None], x, jnp.nan)


def cholesky(a: Array) -> Array:
    """Lower Cholesky factor L (..., d, d) of the symmetric positive-definite ``a``
    (..., d, d), L·Lᵀ = ½(a + aᵀ); all NaN where ``a`` is not positive definite (or not
    finite): NaN like ``jnp.linalg.cholesky``'s, which keeps the upper zeros."""
    if a.shape[-1] > UNROLL_MAX:
        return jnp.linalg.cholesky(a)
    low, ok = _cholesky(a)
    return _nan_where_not(ok, low)


def spd_inv(a: Array) -> Array:
    """(½(a + aᵀ))⁻¹ (..., d, d) of the symmetric positive-definite ``a`` (..., d, d) as
    MᵀM, M = L⁻¹ by forward substitution; all NaN where ``a`` is not positive
    definite."""
    d = a.shape[-1]
    if d > UNROLL_MAX:
        return jnp.linalg.inv(0.5 * (a + jnp.swapaxes(a, -1, -2)))
    low, ok = _cholesky(a)
    m = jnp.zeros_like(low)
    eye = jnp.eye(d, dtype=a.dtype)
    for i in range(d):  # row i of M: (eᵢ − L[i, :i]·M[:i]) / L[i, i]
        row = eye[i] - jnp.sum(low[..., i, :i, None] * m[..., :i, :], -2)
        m = m.at[..., i, :].set(row / low[..., i, i, None])
    return _nan_where_not(ok, _outer_sum(jnp.swapaxes(m, -1, -2), m))


def _outer_sum(a: Array, b: Array) -> Array:
    """(..., n, k) @ (..., k, p) as k outer products (one fused loop; XLA:CPU's batched
    dot runs per matrix)."""
    return sum(a[..., :, i, None] * b[..., None, i, :] for i in range(a.shape[-1]))


def inv(a: Array) -> Array:
    """a⁻¹ (..., d, d) of square ``a`` (..., d, d); inf or NaN where ``a`` is singular.
    d ≤ 3 as adjugate / determinant (a few products, smooth in ``a``: its derivatives of
    every order stay small programs); larger by ``jnp.linalg.inv``."""
    d = a.shape[-1]
    if d == 1:
        return 1.0 / a
    if d == 2:
        det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
        adj = jnp.stack([jnp.stack([a[..., 1, 1], -a[..., 0, 1]], -1),
                         jnp.stack([-a[..., 1, 0], a[..., 0, 0]], -1)], -2)
        return adj / det[..., None, None]
    if d == 3:  # the columns of adj(a) are cross products of a's rows
        r0, r1, r2 = a[..., 0, :], a[..., 1, :], a[..., 2, :]
        cols = [jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)]
        det = jnp.sum(r0 * cols[0], -1)
        return jnp.stack(cols, -1) / det[..., None, None]
    return jnp.linalg.inv(a)


def solve(a: Array, b: Array) -> Array:
    """x (..., d, k) with a·x = b for square ``a`` (..., d, d) and ``b`` (..., d, k):
    d ≤ 3 as :func:`inv` (a)·b, larger by ``jnp.linalg.solve``."""
    if a.shape[-1] > 3:
        return jnp.linalg.solve(a, b)
    return _outer_sum(inv(a), b)


__all__ = ["UNROLL_MAX", "cholesky", "inv", "solve", "spd_inv"]
