"""Point-cloud down-sampling with static output shapes: voxel grid and random subset.

``voxel_filter`` groups points by voxel ``floor((p − min) / size)`` (as PyPose's
``voxel_filter``) and returns one point per occupied voxel — the centroid, or a random
member with ``key`` — in lexicographic voxel order. Because the number of occupied voxels
is data dependent, the output has a fixed capacity ``max_voxels``: the result carries the
points (max_voxels, D), a ``valid`` mask and the true ``count`` (voxels beyond the
capacity are dropped and ``count > max_voxels`` tells so). With ``max_voxels=None`` the
capacity is computed from the data, which needs concrete values (not under ``jit``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..lie.base import as_float_array
from ._util import Array, points_array


class Downsampled(NamedTuple):
    """``points`` (max_voxels, D) (padding rows are zero); ``valid`` (max_voxels,) bool;
    ``count`` () int32: occupied voxels (may exceed max_voxels)."""

    points: Array
    valid: Array
    count: Array


def _voxel_ids(p: Array, size: Array) -> tuple[Array, Array, Array]:
    """Segment id per point (sorted voxel order), the sort order and the voxel count."""
    vdim = size.shape[0]
    cells = jnp.floor((p[:, :vdim] - jnp.min(p[:, :vdim], 0)) / size).astype(jnp.int32)
    order = jnp.lexsort(tuple(cells[:, i] for i in range(vdim - 1, -1, -1)))
    sc = cells[order]
    new = jnp.concatenate([jnp.ones((1,), bool), jnp.any(sc[1:] != sc[:-1], -1)])
    seg_sorted = jnp.cumsum(new) - 1
    count = seg_sorted[-1] + 1
    return seg_sorted, order, count.astype(jnp.int32)


def voxel_filter(
    points: Any,
    voxel: Any,
    max_voxels: int | None = None,
    key: Any = None,
) -> Downsampled:
    """One point per voxel of a cloud (N, D); ``voxel`` (v,) sizes act on the first
    v ≤ D coordinates (the rest, e.g. colours, are averaged or carried along).

    ``key=None``: voxel centroids (all D columns averaged); with a PRNG ``key``: a
    uniformly random member point of each voxel. No batch axes (vmap for batches)."""
    fn = "voxel_filter"
    p = points_array(points, f"{fn}(points)", None, min_points=1)
    if p.ndim != 2:
        raise ValueError(f"{fn}(points): expected shape (N, D) without batch axes (vmap for "
                         f"batches), got {tuple(p.shape)}")
    size = as_float_array(voxel, f"{fn}(voxel)").astype(p.dtype)
    if size.ndim != 1 or not 1 <= size.shape[0] <= p.shape[1]:
        raise ValueError(f"{fn}(voxel): expected sizes of shape (v,) with 1 ≤ v ≤ D = "
                         f"{p.shape[1]}, got shape {tuple(size.shape)}")
    if not isinstance(size, jax.core.Tracer) and not bool(jnp.all(size > 0)):
        raise ValueError(f"{fn}(voxel): sizes must be positive, got {np.asarray(size)}")
    n = p.shape[0]
    seg, order, count = _voxel_ids(p, size)
    if max_voxels is None:
        if isinstance(count, jax.core.Tracer):
            raise TypeError(f"{fn}(max_voxels): the number of voxels is data dependent; pass "
                            f"max_voxels (an int capacity) when calling under jit/vmap")
        max_voxels = int(count)
    if not isinstance(max_voxels, int) or max_voxels < 1:
        raise ValueError(f"{fn}(max_voxels): expected a positive int, got {max_voxels!r}")
    sp = p[order]
    valid = jnp.arange(max_voxels) < count
    seg_c = jnp.where(seg < max_voxels, seg, max_voxels)  # overflow → dropped segment
    if key is None:
        sums = jax.ops.segment_sum(sp, seg_c, num_segments=max_voxels + 1)[:max_voxels]
        cnt = jax.ops.segment_sum(jnp.ones((n,), p.dtype), seg_c,
                                  num_segments=max_voxels + 1)[:max_voxels]
        out = sums / jnp.maximum(cnt, 1)[:, None]
    else:
        prio = jax.random.uniform(key, (n,))
        best = jax.ops.segment_min(prio, seg_c, num_segments=max_voxels + 1)[:max_voxels]
        pos = jnp.arange(n)
        pick = jnp.where(prio == best[jnp.minimum(seg_c, max_voxels - 1)], pos, n)
        chosen = jax.ops.segment_min(pick, seg_c, num_segments=max_voxels + 1)[:max_voxels]
        out = sp[jnp.clip(chosen, 0, n - 1)]
    out = jnp.where(valid[:, None], out, 0.0)
    return Downsampled(out, valid, count)


def random_filter(points: Any, num: int, key: Any) -> Array:
    """``num`` distinct points drawn uniformly from each cloud (..., N, D) → (..., num, D)
    (the same draw for every batch element, as PyPose's ``random_filter``)."""
    p = points_array(points, "random_filter(points)", None, min_points=1)
    n = p.shape[-2]
    if not isinstance(num, int) or not 1 <= num <= n:
        raise ValueError(f"random_filter(num): expected an int with 1 ≤ num ≤ N = {n}, got "
                         f"{num!r}")
    idx = jax.random.choice(key, n, (num,), replace=False)
    return jnp.take(p, idx, axis=-2)


__all__ = ["Downsampled", "random_filter", "voxel_filter"]
