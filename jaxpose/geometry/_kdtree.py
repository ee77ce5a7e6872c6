"""Exact nearest-neighbour search with a balanced k-d tree, in pure JAX.

The tree is *implicit*: the points are permuted so that every node is a contiguous range
``[lo, hi)`` of the permuted array whose splitting point sits at ``mid = lo + (hi−lo)//2``
(left child ``[lo, mid)``, right child ``[mid+1, hi)``). Building it is one segmented sort
per level (``⌊log₂N⌋ + 1`` levels); each range splits along its widest axis. Nothing but
the permuted points, the original indices and one split axis per node is stored.

Queries run a stack-free depth-first search (each query keeps only its current and
previous node; parent/child links are stored per node) with exact pruning: a far subtree
is skipped only when its splitting plane is not closer than the current k-th best
distance. The search is vectorised over a chunk of queries inside one
``lax.while_loop``; chunks are processed by ``lax.map``, so memory is O(N + chunk · k).
Results are exact: ties are the only freedom (either of two equidistant points may be
returned). Everything has static shapes, so building and searching jit and vmap.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..lie._base import runtime_check
from ._util import Array, points_array


class KDTree(NamedTuple):
    """``points`` (M, D) permuted into tree order; ``index`` (M,) int32: the original index
    of each; per node (= position): ``dim`` split axis, ``left`` / ``right`` / ``parent``
    positions (−1 for none); ``position`` (M,): the tree position of each original
    point (the inverse of ``index``); all int32."""

    points: Array
    index: Array
    dim: Array
    left: Array
    right: Array
    parent: Array
    position: Array

    @property
    def depth(self) -> int:
        """Number of tree levels, ⌊log₂ M⌋ + 1 (0 for an empty tree)."""
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
        pts, idx, dims, lo, hi, active, node_lo, node_hi = state
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
        node_lo = jnp.where(settle, lo, node_lo)
        node_hi = jnp.where(settle, hi, node_hi)
        new_hi = jnp.where(active & (pos < mid), mid, hi)
        new_lo = jnp.where(active & (pos > mid), mid + 1, lo)
        return pts, idx, dims, new_lo, new_hi, active & ~settle, node_lo, node_hi

    zeros = jnp.zeros(m, jnp.int32)
    init = (p, pos, zeros, zeros, jnp.full((m,), m, jnp.int32), jnp.ones(m, bool), zeros,
            zeros)
    pts, idx, dims, _, _, _, lo, hi = jax.lax.fori_loop(0, num_levels(m), level, init)
    # children are the midpoints of [lo, pos) and [pos + 1, hi)
    left = jnp.where(lo < pos, lo + (pos - lo) // 2, -1).astype(jnp.int32)
    right = jnp.where(pos + 1 < hi, pos + 1 + (hi - pos - 1) // 2, -1).astype(jnp.int32)
    parent = jnp.full((m,), -1, jnp.int32)
    parent = parent.at[jnp.where(left >= 0, left, m)].set(pos, mode="drop")
    parent = parent.at[jnp.where(right >= 0, right, m)].set(pos, mode="drop")
    position = jnp.zeros((m,), jnp.int32).at[idx].set(pos)
    return KDTree(pts, idx, dims, left, right, parent, position)


def _search_chunk(tree: KDTree, q: Array, k: int, hint: Array | None = None
                  ) -> tuple[Array, Array]:
    """k nearest (squared distance, tree position) for a chunk of queries q (C, D);
    ``hint`` (C,) tree positions of known nearby points (k = 1) seed the bound.

    Stack-free traversal: each lane keeps only (current node, previous node); coming
    down from the parent it visits the node and descends to the near child, coming back
    from the near child it tries the far child (pruned unless the splitting plane is
    closer than the current k-th best), and otherwise it climbs to the parent."""
    c = q.shape[0]
    m = tree.points.shape[0]
    dtype = q.dtype
    lanes = jnp.arange(c)
    root = jnp.asarray(m // 2, jnp.int32)

    def cond(state: tuple[Array, ...]) -> Array:
        return jnp.any(state[0] >= 0)

    def body(state: tuple[Array, ...]) -> tuple[Array, ...]:
        curr, prev, best_d, best_i = state
        live = curr >= 0
        node = jnp.clip(curr, 0, m - 1)
        p = tree.points[node]  # (C, D)
        ax = tree.dim[node]
        diff = q[lanes, ax] - p[lanes, ax]
        go_left = diff < 0
        left, right, parent = tree.left[node], tree.right[node], tree.parent[node]
        near = jnp.where(go_left, left, right)
        far = jnp.where(go_left, right, left)
        from_parent = prev == parent
        from_near = (prev == near) & (near >= 0)
        # visit the node on the way down
        dist = jnp.sum(jnp.square(p - q), -1)
        worst = jnp.max(best_d, -1)
        better = live & from_parent & (dist < worst)
        slot = jnp.argmax(best_d, -1)
        hit = better[:, None] & (jnp.arange(k)[None, :] == slot[:, None])
        best_d = jnp.where(hit, dist[:, None], best_d)
        best_i = jnp.where(hit, node[:, None], best_i)
        worst = jnp.max(best_d, -1)
        far_ok = (far >= 0) & (diff * diff < worst)
        nxt = jnp.where(
            from_parent,
            jnp.where(near >= 0, near, jnp.where(far_ok, far, parent)),
            jnp.where(from_near, jnp.where(far_ok, far, parent), parent),
        )
        return (jnp.where(live, nxt, curr), jnp.where(live, curr, prev), best_d, best_i)

    best_d = jnp.full((c, k), jnp.inf, dtype)
    best_i = jnp.zeros((c, k), jnp.int32)
    if hint is not None:
        d0 = jnp.sum(jnp.square(tree.points[hint] - q), -1)
        best_d = best_d.at[:, 0].set(d0)
        best_i = best_i.at[:, 0].set(hint)
    init = (jnp.full((c,), root), jnp.full((c,), -1, jnp.int32), best_d, best_i)
    _, _, best_d, best_i = jax.lax.while_loop(cond, body, init)
    return best_d, best_i


def query_kdtree(tree: KDTree, query: Any, k: int = 1, chunk: int = 1024,
                 hint: Any = None) -> tuple[Array, Array]:
    """The ``k`` nearest tree points of every query (N, D) (finite: a NaN or inf query
    raises, eagerly or by ``eqx.error_if`` under ``jit``).

    ``hint`` (N,) int: original indices of points believed to be near each query (e.g.
    the previous ICP correspondences; k = 1 only). They only tighten the initial bound, so
    the answer stays exact. Returns (squared distances (N, k) ascending, original indices
    (N, k) int32). No derivatives flow through the search (use the indices to gather and
    differentiate)."""
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
    # a NaN query compares false with every bound: distance inf, an arbitrary index
    q = runtime_check(q, ~jnp.all(jnp.isfinite(q)),
                      "query_kdtree(query): contains NaN or inf (a non-finite query has no "
                      "nearest point; drop or fix those rows first)")
    t = jax.lax.stop_gradient(tree)
    if hint is not None and k != 1:
        raise ValueError("query_kdtree(hint): hints are supported for k = 1 only")
    if hint is not None and np.shape(hint) != (n,):
        raise ValueError(f"query_kdtree(hint): expected shape ({n},) (one index per query), "
                         f"got {np.shape(hint)}")
    c = max(1, min(chunk, n))
    n_chunks = math.ceil(n / c)
    pad = n_chunks * c - n
    qs = jnp.concatenate([q, jnp.broadcast_to(q[:1], (pad, d))], 0).reshape(n_chunks, c, d)
    if hint is None:
        dist, pos = jax.lax.map(lambda qc: _search_chunk(t, qc, k), qs)
    else:
        hp = t.position[jnp.clip(jnp.asarray(hint, jnp.int32), 0, m - 1)]
        hp = jnp.concatenate([hp, jnp.broadcast_to(hp[:1], (pad,))]).reshape(n_chunks, c)
        dist, pos = jax.lax.map(lambda a: _search_chunk(t, a[0], k, a[1]), (qs, hp))
    dist, pos = dist.reshape(-1, k)[:n], pos.reshape(-1, k)[:n]
    order = jnp.argsort(dist, -1)
    dist = jnp.take_along_axis(dist, order, -1)
    pos = jnp.take_along_axis(pos, order, -1)
    return dist, t.index[pos]


__all__ = ["KDTree", "build_kdtree", "num_levels", "query_kdtree"]
