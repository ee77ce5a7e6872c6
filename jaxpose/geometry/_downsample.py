"""Point-cloud down-sampling and outlier removal with static output shapes: voxel grid,
random subset, neighbour-count (``nbr_filter``) and neighbour-average (``knn_filter``)
filters.

``voxel_filter`` groups points by voxel ``floor((p − min) / size)`` (as PyPose's
``voxel_filter``) and returns one point per occupied voxel — the centroid, or a random
member with ``key`` — in lexicographic voxel order. Because the number of occupied voxels
is data dependent, the output has a fixed capacity ``max_voxels``: the result carries the
points (max_voxels, D), a ``valid`` mask and the true ``count`` (voxels beyond the
capacity are dropped and ``count > max_voxels`` tells so). With ``max_voxels=None`` the
capacity is computed from the data, which needs concrete values (not under ``jit``).

``nbr_filter`` and ``knn_filter`` (PyPose's names) keep the input's shape: the kept points
come first in their input order, the result's ``valid`` marks them and ``inlier`` is the
per-input-point mask (PyPose's ``return_mask``). Neighbours are Euclidean, searched with
:func:`~jaxpose.geometry.knn` on the first ``pdim`` coordinates (default: all).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count
from ..lie._base import as_float_array, runtime_check
from ._knn import knn
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
    # a NaN point made the grid origin NaN (every finite point merged into one voxel with
    # a NaN centroid); inf blamed the voxel size
    x = runtime_check(p[:, :vdim], ~jnp.all(jnp.isfinite(p[:, :vdim])),
                      "voxel_filter(points): the voxelised coordinates contain NaN or inf")
    cells = jnp.floor((x - jnp.min(x, 0)) / size)
    cells = runtime_check(cells, jnp.any(cells >= np.iinfo(np.int32).max),
                          "voxel_filter(voxel): sizes too small for the extent of the points "
                          "(more than 2³¹ − 1 voxels along an axis)").astype(jnp.int32)
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
    size = runtime_check(size, ~jnp.all(size > 0), f"{fn}(voxel): sizes must be positive")
    n = p.shape[0]
    seg, order, count = _voxel_ids(p, size)
    if max_voxels is None:
        if isinstance(count, jax.core.Tracer):
            raise TypeError(f"{fn}(max_voxels): the number of voxels is data dependent; pass "
                            f"max_voxels (an int capacity) when calling under jit/vmap")
        max_voxels = int(count)
    max_voxels = check_count(max_voxels, f"{fn}(max_voxels)")
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


class Filtered(NamedTuple):
    """``points`` (..., N, D): the kept points first, in input order (padding rows are
    zero); ``valid`` (..., N) bool marks them; ``count`` (...) int32 kept points;
    ``inlier`` (..., N) bool: which input points were kept."""

    points: Array
    valid: Array
    count: Array
    inlier: Array


def _compact(p: Array, keep: Array) -> Filtered:
    """Move the rows of ``p`` (..., N, D) with ``keep`` to the front (stable order)."""
    order = jnp.argsort(~keep, axis=-1, stable=True)
    count = jnp.sum(keep, -1).astype(jnp.int32)
    valid = jnp.arange(keep.shape[-1]) < count[..., None]
    out = jnp.take_along_axis(p, order[..., None], axis=-2)
    return Filtered(jnp.where(valid[..., None], out, 0.0), valid, count, keep)


def _neighbour_args(fn: str, points: Any, count_name: str, count: Any, pdim: Any
                    ) -> tuple[Array, int]:
    p = points_array(points, f"{fn}(points)", None, min_points=1)
    d = p.shape[-1]
    if pdim is None:
        pdim = d
    if not isinstance(pdim, int) or isinstance(pdim, bool) or not 1 <= pdim <= d:
        raise ValueError(f"{fn}(pdim): expected an int with 1 ≤ pdim ≤ D = {d}, got {pdim!r}")
    check_count(count, f"{fn}({count_name})")
    return p, pdim


def _radius_inliers(fn: str, p: Array, pdim: int, nbr: int, radius: Any) -> Array:
    """(..., N) bool: at least ``nbr`` other points within ``radius`` (inclusive)."""
    r = as_float_array(radius, f"{fn}(radius)").astype(p.dtype)
    if r.ndim != 0:
        raise ValueError(f"{fn}(radius): expected a scalar, got shape {tuple(r.shape)}")
    if isinstance(r, jax.core.Tracer):
        r = runtime_check(r, ~(r >= 0), f"{fn}(radius): expected a non-negative radius "
                                         "(checked under jit)")
    elif not bool(r >= 0):
        raise ValueError(f"{fn}(radius): expected a non-negative radius, got {float(r)}")
    n = p.shape[-2]
    if nbr + 1 > n:  # fewer points than nbr + 1: nobody has nbr neighbours
        return jnp.zeros(p.shape[:-1], bool)
    x = jax.lax.stop_gradient(p[..., :pdim])
    # the (nbr+1)-th nearest point, counting the point itself, lies within the radius
    # exactly when at least nbr others do
    return knn(x, x, nbr + 1).distances[..., nbr] <= r


def nbr_filter(points: Any, nbr: int, radius: Any, pdim: int | None = None) -> Filtered:
    """Radius outlier removal: keep the points of a cloud (..., N, D) that have at least
    ``nbr`` other points within ``radius`` (distance on the first ``pdim`` coordinates).

    Returns :class:`Filtered` (static shapes; see the module docstring)."""
    p, pdim = _neighbour_args("nbr_filter", points, "nbr", nbr, pdim)
    return _compact(p, _radius_inliers("nbr_filter", p, pdim, nbr, radius))


def knn_filter(points: Any, k: int, radius: Any = None, pdim: int | None = None
               ) -> Filtered:
    """Statistical smoothing of a cloud (..., N, D): each point is replaced by the mean of
    itself and its ``k`` nearest neighbours (all D columns averaged, neighbours found on
    the first ``pdim`` coordinates among all input points). With ``radius``, points with
    fewer than ``k`` neighbours within it are dropped (as :func:`nbr_filter`).

    Returns :class:`Filtered`; differentiable with respect to the coordinates (the
    neighbour selection is piecewise constant)."""
    p, pdim = _neighbour_args("knn_filter", points, "k", k, pdim)
    n = p.shape[-2]
    if k + 1 > n:
        raise ValueError(f"knn_filter(k): k = {k} needs at least k + 1 = {k + 1} points, got "
                         f"N = {n}")
    x = jax.lax.stop_gradient(p[..., :pdim])
    idx = knn(x, x, k + 1).indices  # (..., N, k+1), the point itself included
    flat = idx.reshape(*idx.shape[:-2], -1)[..., None]  # (..., N·(k+1), 1)
    nb = jnp.take_along_axis(p, flat, axis=-2).reshape(*idx.shape, p.shape[-1])
    smoothed = jnp.mean(nb, axis=-2)
    keep = (jnp.ones(p.shape[:-1], bool) if radius is None
            else _radius_inliers("knn_filter", p, pdim, k, radius))
    return _compact(smoothed, keep)


__all__ = ["Downsampled", "Filtered", "knn_filter", "nbr_filter", "random_filter",
           "voxel_filter"]
