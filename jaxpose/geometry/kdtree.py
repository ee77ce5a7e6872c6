"""Exact nearest-neighbour search with a balanced k-d tree, in pure JAX.

The tree is *implicit*: the points are permuted so that every node is a contiguous range
``[lo, hi)`` of the permuted array whose splitting point sits at ``mid = lo + (hi−lo)//2``
(left child ``[lo, mid)``, right child ``[mid+1, hi)``). Building it is one segmented sort
per level (``⌊log₂N⌋ + 1`` levels); each range splits along its widest axis. Nothing but
the permuted points, the original indices and one split axis per node is stored.

Queries run a best-first-by-stack search with exact pruning (a subtree is skipped only
when its half-space lower bound is not smaller than the current k-th best squared
distance), vectorised over a chunk of queries inside one ``lax.while_loop``; chunks are
processed by ``lax.map``, so memory is O(N + chunk · (depth + k)). Results are exact: ties
are the only freedom (either of two equidistant points may be returned). Everything has
static shapes, so building and searching jit and vmap.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ._util import Array, points_array


class KDTree(NamedTuple):
    """``points`` (M, D) permuted into tree order; ``index`` (M,) int32: the original index
    of each; ``dim`` (M,) int32: the split axis of the node at each position."""

    points: Array
    index: Array
    dim: Array

    @property
    def depth(self) -> int:
        return num_levels(self.points.shape[0])


def num_levels(m: int) -> int:
    """Levels of the implicit tree over m points (⌊log₂ m⌋ + 1; 0 for m = 0)."""
    return max(int(m).bit_length(), 0)


def build_kdtree(points: Any) -> KDTree:
    """Build the implicit k-d tree of ``points`` (M, D), M ≥ 1 (no batch axes). Points
    with NaN/Inf coordinates are stored far away so they are never returned for a finite
    query while a finite point exists."""
    p = points_array(points, "build_kdtree(points)", None, min_points=1)
    if p.ndim != 2:
        raise ValueError(f"build_kdtree(points): expected shape (M, D) without batch axes "
                         f"(vmap for batches), got {tuple(p.shape)}")
    m, d = p.shape
    pos = jnp.arange(m, dtype=jnp.int32)
    # non-finite points move far away (never nearer than a finite point)
    far = jnp.sqrt(jnp.finfo(p.dtype).max) / 4
    p = jnp.where(jnp.all(jnp.isfinite(p), -1, keepdims=True), p, far)

    def level(_: int, state: tuple[Array, ...]) -> tuple[Array, ...]:
        pts, idx, dims, lo, hi, active = state
        # one segment per active range (key = lo); settled positions key on themselves
        key = jnp.where(active, lo, pos)
        big = jnp.asarray(jnp.inf, pts.dtype)
        seg_max = jax.ops.segment_max(jnp.where(active[:, None], pts, -big), key,
                                      num_segments=m)
        seg_min = jax.ops.segment_min(jnp.where(active[:, None], pts, big), key,
                                      num_segments=m)
        axis = jnp.argmax(seg_max - seg_min, -1).astype(jnp.int32)[key]  # per position
        coord = jnp.take_along_axis(pts, axis[:, None], 1)[:, 0]
        coord = jnp.where(active, coord, 0.0)
        order = jnp.lexsort((coord, key))
        pts, idx = pts[order], idx[order]
        mid = lo + (hi - lo) // 2
        settle = active & (pos == mid)
        dims = jnp.where(settle, axis, dims)
        new_hi = jnp.where(active & (pos < mid), mid, hi)
        new_lo = jnp.where(active & (pos > mid), mid + 1, lo)
        return pts, idx, dims, new_lo, new_hi, active & ~settle

    init = (p, pos, jnp.zeros(m, jnp.int32), jnp.zeros(m, jnp.int32),
            jnp.full((m,), m, jnp.int32), jnp.ones(m, bool))
    pts, idx, dims, *_ = jax.lax.fori_loop(0, num_levels(m), level, init)
    return KDTree(pts, idx, dims)


def _search_chunk(tree: KDTree, q: Array, k: int) -> tuple[Array, Array]:
    """k nearest (squared distance, tree position) for a chunk of queries q (C, D)."""
    c = q.shape[0]
    m = tree.points.shape[0]
    s = num_levels(m) + 2  # stack depth: one far child per level plus the current node
    dtype = q.dtype
    inf = jnp.asarray(jnp.inf, dtype)
    slots = jnp.arange(s, dtype=jnp.int32)
    lanes = jnp.arange(c)

    st_lo = jnp.zeros((c, s), jnp.int32)
    st_hi = jnp.zeros((c, s), jnp.int32).at[:, 0].set(m)
    st_b = jnp.zeros((c, s), dtype)
    sp = jnp.ones((c,), jnp.int32)
    best_d = jnp.full((c, k), inf)
    best_i = jnp.zeros((c, k), jnp.int32)

    def cond(state: tuple[Array, ...]) -> Array:
        return jnp.any(state[3] > 0)

    def body(state: tuple[Array, ...]) -> tuple[Array, ...]:
        st_lo, st_hi, st_b, sp, best_d, best_i = state
        live = sp > 0
        top = jnp.maximum(sp - 1, 0)
        lo, hi, bound = st_lo[lanes, top], st_hi[lanes, top], st_b[lanes, top]
        worst = jnp.max(best_d, -1)
        visit = live & (lo < hi) & (bound < worst)
        mid = jnp.clip(lo + (hi - lo) // 2, 0, m - 1)
        node = tree.points[mid]  # (C, D)
        dist = jnp.sum(jnp.square(node - q), -1)
        # replace the current worst of the k best
        better = visit & (dist < worst)
        slot = jnp.argmax(best_d, -1)
        hit = better[:, None] & (jnp.arange(k)[None, :] == slot[:, None])
        best_d = jnp.where(hit, dist[:, None], best_d)
        best_i = jnp.where(hit, mid[:, None], best_i)
        # children: near first (pushed last)
        ax = tree.dim[mid]
        diff = jnp.take_along_axis(q, ax[:, None], 1)[:, 0] - node[lanes, ax]
        go_left = diff < 0
        left = (lo, mid)
        right = (mid + 1, hi)
        near_lo = jnp.where(go_left, left[0], right[0])
        near_hi = jnp.where(go_left, left[1], right[1])
        far_lo = jnp.where(go_left, right[0], left[0])
        far_hi = jnp.where(go_left, right[1], left[1])
        far_b = jnp.maximum(bound, diff * diff)
        # pop, then (if visited) push far at top and near at top + 1
        at0 = (slots[None, :] == top[:, None]) & visit[:, None]
        at1 = (slots[None, :] == (top + 1)[:, None]) & visit[:, None]
        st_lo = jnp.where(at0, far_lo[:, None], jnp.where(at1, near_lo[:, None], st_lo))
        st_hi = jnp.where(at0, far_hi[:, None], jnp.where(at1, near_hi[:, None], st_hi))
        st_b = jnp.where(at0, far_b[:, None], jnp.where(at1, bound[:, None], st_b))
        sp = jnp.where(visit, sp + 1, jnp.where(live, sp - 1, sp))
        return st_lo, st_hi, st_b, sp, best_d, best_i

    state = jax.lax.while_loop(cond, body, (st_lo, st_hi, st_b, sp, best_d, best_i))
    return state[4], state[5]


def query_kdtree(tree: KDTree, query: Any, k: int = 1, chunk: int = 2048) -> tuple[Array,
                                                                                   Array]:
    """The ``k`` nearest tree points of every query (N, D).

    Returns (squared distances (N, k) ascending, original indices (N, k) int32). No
    derivatives flow through the search (use the indices to gather and differentiate)."""
    q = points_array(query, "query_kdtree(query)", tree.points.shape[-1], min_points=0)
    if q.ndim != 2:
        raise ValueError(f"query_kdtree(query): expected shape (N, D), got {tuple(q.shape)}")
    m = tree.points.shape[0]
    if not isinstance(k, int) or k < 1 or k > m:
        raise ValueError(f"query_kdtree(k): expected 1 ≤ k ≤ M = {m}, got {k!r}")
    n, d = q.shape
    if n == 0:
        return jnp.zeros((0, k), q.dtype), jnp.zeros((0, k), jnp.int32)
    q = jax.lax.stop_gradient(q.astype(tree.points.dtype))
    t = jax.lax.stop_gradient(tree)
    c = max(1, min(chunk, n))
    n_chunks = math.ceil(n / c)
    pad = n_chunks * c - n
    qs = jnp.concatenate([q, jnp.broadcast_to(q[:1], (pad, d))], 0).reshape(n_chunks, c, d)
    dist, pos = jax.lax.map(lambda qc: _search_chunk(t, qc, k), qs)
    dist, pos = dist.reshape(-1, k)[:n], pos.reshape(-1, k)[:n]
    order = jnp.argsort(dist, -1)
    dist = jnp.take_along_axis(dist, order, -1)
    pos = jnp.take_along_axis(pos, order, -1)
    return dist, t.index[pos]


__all__ = ["KDTree", "build_kdtree", "num_levels", "query_kdtree"]
