"""Exact k-nearest neighbours by brute force, tiled so memory stays bounded.

``knn(query, points, k)`` compares every query with every point, one tile of queries at a
time (``lax.map`` over tiles), so the largest temporary is a (tile, M) block of
distances whose size is set by ``budget`` — 100k × 100k searches run in a few tens of
MB. Distances are Euclidean (PyPose's ``ord=2``).

Selection. With ``precise=False`` (default) the tile is scored with the expanded form
``|p|² − 2 q·p`` around the points' centroid (a matrix product, several times faster
on CPU); squared distances that differ by less than about ``16·eps·(R² + |q|²)`` (R the
cloud radius about its centroid) count as ties, and the lower index wins. With
``precise=True`` the tile holds ``Σ (q − p)²`` and ties are exact up to rounding of the
difference itself. In both cases the returned distances are recomputed from the
coordinates of the selected points (so they are exact and differentiable with respect
to ``query`` and ``points``; the indices are integers and carry no derivative).

For k = 1 the index is found with two min-reductions (the minimum, then the lowest
index attaining it), which XLA vectorises far better than ``argmin``; for k > 1
``lax.top_k`` picks the candidates.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from .._checks import check_count
from .._precision import full_precision
from .._safe import safe_norm
from ..lie._base import runtime_check
from ._kdtree import build_kdtree, query_kdtree
from ._util import Array, batch_shape, flatten_batch, points_array

DEFAULT_BUDGET = 1 << 22  # elements of the (tile, M) distance block (16 MiB in float32)
"""Default ``budget``: elements of one (tile, M) block of distances (16 MiB in float32)."""
AUTO_KDTREE_PAIRS = 1 << 27  # "auto" switches to the k-d tree on CPU from ~11k × 11k
"""``method="auto"`` uses the k-d tree on CPU when N·M exceeds this (from ~11k × 11k)."""


class KNNResult(NamedTuple):
    """``distances`` (..., N, k), ascending; ``indices`` (..., N, k) int32 into ``points``."""

    distances: Array
    indices: Array


def tile_size(n_query: int, n_points: int, budget: int = DEFAULT_BUDGET) -> int:
    """Queries per tile so a (tile, n_points) block has at most ``budget`` elements."""
    t = max(1, budget // max(n_points, 1))
    if t >= 8:
        t = t // 8 * 8
    return max(1, min(t, n_query))


def _scores(qt: Array, p: Array, sq: Array, precise: bool) -> Array:
    """(T, M) scores, monotone in the squared distance per row."""
    if precise:  # per-coordinate sum keeps it one fused elementwise-reduce
        out = jnp.square(qt[:, 0:1] - p[None, :, 0])
        for i in range(1, qt.shape[1]):
            out = out + jnp.square(qt[:, i:i + 1] - p[None, :, i])
        return out
    return sq[None, :] - 2.0 * (qt @ p.T)


def _select(q: Array, p: Array, k: int, tile: int, precise: bool) -> Array:
    """Indices (N, k) of the k nearest points (no derivatives)."""
    n, d = q.shape
    m = p.shape[0]
    dtype = q.dtype
    ok = jnp.all(jnp.isfinite(p), -1)  # non-finite points are never selected
    center = jnp.sum(jnp.where(ok[:, None], p, 0.0), 0) / jnp.maximum(jnp.sum(ok), 1)
    pc = jnp.where(ok[:, None], p - center, 0.0)
    qc = q - center
    sq = jnp.where(ok, jnp.sum(pc * pc, -1), jnp.inf)
    if precise:  # the difference form cannot carry the +inf penalty: push them far away
        pc = jnp.where(ok[:, None], pc, jnp.sqrt(jnp.finfo(dtype).max) / 4)
    n_tiles = math.ceil(n / tile)
    pad = n_tiles * tile - n
    qt_all = jnp.concatenate([qc, jnp.zeros((pad, d), dtype)], 0).reshape(n_tiles, tile, d)

    if k > 1:
        def topk(qt: Array) -> Array:
            return jax.lax.top_k(-_scores(qt, pc, sq, precise), k)[1]

        idx = jax.lax.map(topk, qt_all)
        return idx.reshape(n_tiles * tile, k)[:n].astype(jnp.int32)

    # k = 1: pass 1 finds the minimum score per query, pass 2 the lowest index attaining
    # it — both plain min-reductions over the same expression (bitwise-identical scores;
    # a tile where pass 2 finds no hit falls back to argmin, so the result never depends
    # on that).
    mins = jax.lax.map(lambda qt: jnp.min(_scores(qt, pc, sq, precise), -1), qt_all)
    iota_i = jnp.arange(m, dtype=jnp.int32)
    loose = 16 * jnp.finfo(dtype).eps * jnp.max(jnp.abs(sq))

    def fallback(qt: Array, mt: Array) -> Array:
        """Lowest index within a loose rounding tolerance of the minimum (m if none)."""
        tol = loose + 16 * jnp.finfo(dtype).eps * (jnp.abs(mt) + jnp.sum(qt * qt, -1))
        hit = _scores(qt, pc, sq, precise) <= (mt + tol)[:, None]
        return jnp.min(jnp.where(hit, iota_i[None, :], m), -1)

    if m < (1 << (jnp.finfo(dtype).nmant + 1)):  # indices exact in the float type
        iota = jnp.arange(m, dtype=dtype)
        big = jnp.asarray(jnp.finfo(dtype).max / 1e8, dtype)

        def second(args: tuple[Array, Array]) -> Array:
            qt, mt = args
            over = jnp.maximum(_scores(qt, pc, sq, precise) - mt[:, None], 0.0)
            found = jnp.min(over * big + iota[None, :], -1)
            ok = found < m  # False for Inf/NaN too
            exact = jnp.where(ok, found, 0.0).astype(jnp.int32)
            return jax.lax.cond(jnp.all(ok), lambda: exact,
                                lambda: jnp.where(ok, exact, fallback(qt, mt)))
    else:  # more points than the float type counts exactly: integer select

        def second(args: tuple[Array, Array]) -> Array:
            return fallback(*args)

    idx = jax.lax.map(second, (qt_all, mins))
    return jnp.clip(idx, 0, m - 1).astype(jnp.int32).reshape(n_tiles * tile, 1)[:n]


@functools.partial(jax.jit, static_argnames=("k", "use_tree", "tile", "precise"))
def _indices(qf: Array, pf: Array, *, k: int, use_tree: bool, tile: int, precise: bool
             ) -> Array:
    """Neighbour indices (B, N, k) for flattened batches (B, N, D), (B, M, D)."""

    def sel(qp: tuple[Array, Array]) -> Array:
        if use_tree:
            return query_kdtree(build_kdtree(qp[1]), qp[0], k)[1]
        return _select(qp[0], qp[1], k, tile, precise)

    if qf.shape[0] == 1:
        return sel((qf[0], pf[0]))[None]
    return jax.lax.map(sel, (qf, pf))


def resolve_method(method: str, n: int, m: int) -> str:
    """``"auto"`` → ``"kdtree"`` on CPU for searches of at least ``AUTO_KDTREE_PAIRS``
    query-point pairs, ``"brute"`` otherwise (accelerators favour brute force)."""
    if method not in ("auto", "brute", "kdtree"):
        raise ValueError(f"knn(method): expected 'auto', 'brute' or 'kdtree', got {method!r}")
    if method != "auto":
        return method
    cpu = jax.default_backend() == "cpu"
    return "kdtree" if cpu and n * m >= AUTO_KDTREE_PAIRS else "brute"


@full_precision
def knn(
    query: Any,
    points: Any,
    k: int = 1,
    *,
    squared: bool = False,
    method: str = "auto",
    precise: bool = False,
    tile: int | None = None,
    budget: int = DEFAULT_BUDGET,
) -> KNNResult:
    """The ``k`` nearest ``points`` (..., M, D) of every ``query`` (..., N, D).

    ``method``: ``"brute"`` (tiled exhaustive search, see the module docstring),
    ``"kdtree"`` (:mod:`~jaxpose.geometry.kdtree`, exact, O(N log M) on average) or
    ``"auto"`` (see :func:`resolve_method`). Leading batch axes broadcast (batches are
    processed one after another so memory stays bounded). ``tile``: queries per tile of the
    brute-force search (default from ``budget``, the number of elements of one (tile, M)
    distance block). ``squared=True`` returns squared distances. Non-finite points are
    never selected; a non-finite query raises (eagerly, or ``eqx.error_if`` under ``jit``).

    Returns :class:`KNNResult` (distances (..., N, k) ascending, indices (..., N, k))."""
    q = points_array(query, "knn(query)", None, min_points=0)
    p = points_array(points, "knn(points)", None, min_points=1)
    if q.shape[-1] != p.shape[-1]:
        raise ValueError(f"knn(query, points): expected the same point dimension, got "
                         f"{q.shape[-1]} and {p.shape[-1]} (shapes {tuple(q.shape)} and "
                         f"{tuple(p.shape)})")
    k = check_count(k, "knn(k)")
    m = p.shape[-2]
    if k > m:
        raise ValueError(f"knn(k): k = {k} exceeds the number of points M = {m}")
    if tile is not None:
        tile = check_count(tile, "knn(tile)")
    batch = batch_shape(q.shape[:-2], p.shape[:-2], names=("query", "points"))
    dtype = jnp.result_type(q.dtype, p.dtype)
    q, p = q.astype(dtype), p.astype(dtype)
    # both methods: brute force gave a NaN distance and an arbitrary index, the tree raised
    q = runtime_check(q, ~jnp.all(jnp.isfinite(q)),
                      "knn(query): contains NaN or inf (a non-finite query has no nearest "
                      "point; drop or fix those rows first)")
    n = q.shape[-2]
    if n == 0:
        return KNNResult(jnp.zeros((*batch, 0, k), dtype), jnp.zeros((*batch, 0, k), jnp.int32))
    t = tile_size(n, m, budget) if tile is None else min(tile, n)
    use_tree = resolve_method(method, n, m) == "kdtree"

    qf = flatten_batch(q, batch, 2)
    pf = flatten_batch(p, batch, 2)
    idx = _indices(jax.lax.stop_gradient(qf), jax.lax.stop_gradient(pf), k=k,
                   use_tree=use_tree, tile=t, precise=precise)
    # exact distances from the selected coordinates (differentiable)
    nb = jax.vmap(lambda pts, ii: pts[ii])(pf, idx)  # (B, N, k, D)
    diff = qf[:, :, None, :] - nb
    dist = jnp.sum(diff * diff, -1) if squared else safe_norm(diff)
    if k > 1:  # order by the exact distances
        order = jnp.argsort(dist, -1)
        dist = jnp.take_along_axis(dist, order, -1)
        idx = jnp.take_along_axis(idx, order, -1)
    return KNNResult(dist.reshape(*batch, n, k), idx.reshape(*batch, n, k))


__all__ = ["AUTO_KDTREE_PAIRS", "DEFAULT_BUDGET", "KNNResult", "knn", "resolve_method",
           "tile_size"]
