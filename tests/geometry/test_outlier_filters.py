"""Neighbour-count and neighbour-average point filters (PyPose's ``nbr_filter`` /
``knn_filter``) against brute-force numpy references; PyPose parity (peer)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.geometry import knn_filter, nbr_filter

from .conftest import pypose

DOC_POINTS = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 1], [10, 1, 1], [10, 1, 10]])


def _neighbour_counts(p: np.ndarray, radius: float, pdim: int) -> np.ndarray:
    d = np.linalg.norm(p[:, None, :pdim] - p[None, :, :pdim], axis=-1)
    return (d <= radius).sum(-1) - 1


def _knn_means(p: np.ndarray, k: int, pdim: int) -> np.ndarray:
    d = np.linalg.norm(p[:, None, :pdim] - p[None, :, :pdim], axis=-1)
    idx = np.argsort(d, axis=1, kind="stable")[:, : k + 1]
    return p[idx].mean(1)


def test_nbr_filter_brute_force_and_static_shapes(rng):
    p = rng.uniform(size=(80, 4))
    p[:5, :3] += 5.0  # isolated points
    out = nbr_filter(p, 3, 0.3, pdim=3)
    keep = _neighbour_counts(p, 0.3, 3) >= 3
    np.testing.assert_array_equal(out.inlier, keep)
    assert int(out.count) == keep.sum() and out.points.shape == p.shape
    np.testing.assert_array_equal(out.points[: keep.sum()], p[keep])  # input order kept
    assert np.all(np.asarray(out.points[keep.sum():]) == 0) and not out.valid[keep.sum():].any()
    # the documented example: two far points dropped at radius 5, one at radius 12
    np.testing.assert_array_equal(nbr_filter(DOC_POINTS, 2, 5.0).inlier, [1, 1, 1, 1, 0, 0])
    np.testing.assert_array_equal(nbr_filter(DOC_POINTS, 2, 12.0).inlier, [1, 1, 1, 1, 1, 0])
    # fewer points than nbr + 1: nothing can be kept
    assert int(nbr_filter(DOC_POINTS[:2], 2, 100.0).count) == 0


def test_knn_filter_brute_force_jit_vmap_grad(rng):
    p = rng.normal(size=(3, 40, 3))
    out = jax.jit(lambda x: knn_filter(x, 4))(p)
    ref = np.stack([_knn_means(x, 4, 3) for x in p])
    np.testing.assert_allclose(out.points, ref, atol=1e-12)
    assert bool(out.valid.all()) and out.count.tolist() == [40, 40, 40]
    vm = jax.vmap(lambda x: knn_filter(x, 4, radius=0.8).points)(p)
    for b in range(3):
        keep = _neighbour_counts(p[b], 0.8, 3) >= 4
        np.testing.assert_allclose(vm[b, : keep.sum()], _knn_means(p[b], 4, 3)[keep],
                                   atol=1e-12)
    # the mean is linear in the points for a fixed neighbour selection
    w = rng.normal(size=(40, 3))
    g = jax.grad(lambda x: jnp.sum(knn_filter(x, 4).points * w))(p[0])
    d = np.linalg.norm(p[0][:, None] - p[0][None], axis=-1)
    sel = np.argsort(d, axis=1, kind="stable")[:, :5]
    expect = np.zeros_like(w)
    for i in range(40):
        expect[sel[i]] += w[i] / 5
    np.testing.assert_allclose(g, expect, atol=1e-12)
    f32 = knn_filter(p[0].astype(np.float32), 4)
    assert f32.points.dtype == jnp.float32
    np.testing.assert_allclose(f32.points, ref[0], atol=1e-5)


def test_filters_bad_input():
    with pytest.raises(ValueError, match=r"nbr_filter\(nbr\)"):
        nbr_filter(DOC_POINTS, 0, 1.0)
    with pytest.raises(ValueError, match=r"nbr_filter\(radius\)"):
        nbr_filter(DOC_POINTS, 1, -1.0)
    with pytest.raises(ValueError, match=r"knn_filter\(pdim\)"):
        knn_filter(DOC_POINTS, 1, pdim=4)
    with pytest.raises(ValueError, match=r"knn_filter\(k\)"):
        knn_filter(DOC_POINTS, 6)
    with pytest.raises(ValueError, match=r"knn_filter\(points\)"):
        knn_filter(np.zeros(3), 1)


@pytest.mark.peer
def test_filters_match_pypose(rng):
    pp = pypose()
    import torch

    p = rng.normal(size=(50, 4))
    ours = knn_filter(p, 3, pdim=3)
    theirs = pp.knn_filter(torch.tensor(p), k=3, pdim=3).numpy()
    np.testing.assert_allclose(ours.points, theirs, atol=1e-12)
    # with a radius PyPose gathers neighbours from the already-filtered cloud (indices of
    # the unfiltered one), which is only consistent when no inlier's neighbour follows an
    # outlier: its docstring example
    ours = knn_filter(DOC_POINTS, 2, radius=5.0)
    theirs = pp.knn_filter(torch.tensor(DOC_POINTS), k=2, radius=5).numpy()
    np.testing.assert_allclose(ours.points[: int(ours.count)], theirs, atol=1e-12)
    pts, mask = pp.nbr_filter(torch.tensor(p), nbr=3, radius=1.0, pdim=3, return_mask=True)
    ours = nbr_filter(p, 3, 1.0, pdim=3)
    np.testing.assert_array_equal(ours.inlier, mask.numpy())
    np.testing.assert_allclose(ours.points[: int(ours.count)], pts.numpy())
