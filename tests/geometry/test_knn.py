"""k-nearest neighbours (tiled brute force and k-d tree) against numpy brute force."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.geometry import build_kdtree, knn, query_kdtree
from jaxpose.geometry._knn import tile_size


def _reference(q: np.ndarray, p: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    d = np.sqrt(((q[:, None, :] - p[None, :, :]) ** 2).sum(-1))
    idx = np.argsort(d, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(d, idx, 1), idx


@pytest.mark.parametrize("method", ["brute", "kdtree"])
@pytest.mark.parametrize("k", [1, 4])
def test_matches_numpy(rng, method, k):
    q = rng.normal(size=(203, 3))
    p = rng.normal(size=(157, 3)) * np.array([3.0, 1.0, 0.2])  # anisotropic cloud
    res = jax.jit(lambda a, b: knn(a, b, k, method=method, tile=16))(q, p)
    d_ref, i_ref = _reference(q, p, k)
    np.testing.assert_array_equal(res.indices, i_ref)
    np.testing.assert_allclose(res.distances, d_ref, rtol=1e-13)


def test_batched_2d_float32_and_precise(rng):
    q = rng.uniform(size=(2, 50, 2)).astype(np.float32)
    p = rng.uniform(size=(2, 40, 2)).astype(np.float32)
    for method, precise in [("brute", False), ("brute", True), ("kdtree", False)]:
        res = knn(q, p, 2, method=method, precise=precise)
        assert res.distances.dtype == jnp.float32 and res.indices.shape == (2, 50, 2)
        for b in range(2):
            d_ref, i_ref = _reference(q[b].astype(np.float64), p[b].astype(np.float64), 2)
            np.testing.assert_allclose(res.distances[b], d_ref, rtol=1e-5, atol=1e-6)
            assert np.mean(np.asarray(res.indices[b]) == i_ref) > 0.99  # float32 near-ties


def test_kdtree_duplicates_clusters_and_single_point(rng):
    p = np.concatenate([np.repeat(rng.normal(size=(5, 3)), 8, 0), rng.normal(size=(9, 3)) * 50])
    q = np.concatenate([p[:10] + 1e-9, rng.normal(size=(20, 3)) * 60])
    tree = jax.jit(build_kdtree)(p)
    d2, idx = jax.jit(lambda t, a: query_kdtree(t, a, 3))(tree, q)
    d_ref, _ = _reference(q, p, 3)
    np.testing.assert_allclose(np.sqrt(d2), d_ref, rtol=1e-9, atol=1e-12)
    # returned indices really have those distances
    np.testing.assert_allclose(np.linalg.norm(q[:, None] - p[np.asarray(idx)], axis=-1), d_ref,
                               rtol=1e-9, atol=1e-12)
    one = knn(q, p[:1], 1, method="kdtree")
    np.testing.assert_array_equal(one.indices, 0)


@pytest.mark.parametrize("method", ["brute", "kdtree"])
def test_non_finite_points_are_never_selected(rng, method):
    p = rng.normal(size=(30, 3))
    p[[3, 17]] = [np.nan, 0, 0], [np.inf, 1, 1]
    q = p[[0, 3, 5]] + 1e-3
    q[1] = [0.1, 0.2, 0.3]
    res = knn(q, p, 2, method=method)
    assert not np.isin(np.asarray(res.indices), [3, 17]).any()
    assert np.all(np.isfinite(res.distances))


def test_query_tiling_is_invariant(rng):
    q, p = rng.normal(size=(37, 3)), rng.normal(size=(29, 3))
    f = jax.jit(lambda a, b: knn(a, b, 1, method="brute", tile=5).indices)
    g = jax.jit(lambda a, b: knn(a, b, 1, method="brute", budget=29 * 37).indices)
    np.testing.assert_array_equal(f(q, p), g(q, p))
    assert tile_size(100_000, 100_000) * 100_000 <= 1 << 22


def test_gradient_of_distances(rng):
    q, p = jnp.asarray(rng.normal(size=(6, 3))), jnp.asarray(rng.normal(size=(9, 3)))
    res = knn(q, p, 1)
    g = jax.jit(jax.grad(lambda a: jnp.sum(knn(a, p, 1).distances)))(q)
    near = p[res.indices[:, 0]]
    want = (q - near) / np.linalg.norm(q - near, axis=-1, keepdims=True)
    np.testing.assert_allclose(g, want, rtol=1e-12)
    # a query on a point: distance 0, derivative 0 (not NaN)
    g0 = jax.grad(lambda a: jnp.sum(knn(a, p, 1).distances))(p[:2])
    np.testing.assert_array_equal(g0, 0.0)
    # vmap over queries equals the batched call
    vm = jax.vmap(lambda a: knn(a[None], p, 2).indices[0])(q)
    np.testing.assert_array_equal(vm, knn(q, p, 2).indices)


def test_bad_input():
    z3 = np.zeros((4, 3))
    with pytest.raises(ValueError, match=r"knn\(points\).*empty"):
        knn(z3, np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"knn\(k\).*exceeds.*M = 4"):
        knn(z3, z3, 5)
    with pytest.raises(ValueError, match=r"knn\(query, points\).*same point dimension"):
        knn(z3, np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"knn\(method\)"):
        knn(z3, z3, method="ball")
    with pytest.raises(ValueError, match=r"build_kdtree\(points\).*without batch"):
        build_kdtree(np.zeros((2, 4, 3)))
    assert knn(np.zeros((0, 3)), z3).indices.shape == (0, 1)


@pytest.mark.slow
def test_100k_bounded_memory_and_exact_sample(rng):
    """100k × 100k: the compiled program's temporaries stay far below the dense N × M
    matrix (40 GB in float32), and sampled answers are exact."""
    n = 100_000
    q = jnp.asarray(rng.normal(size=(n, 3)), jnp.float32)
    p = jnp.asarray(rng.normal(size=(n, 3)), jnp.float32)
    for method in ("kdtree", "brute"):
        f = jax.jit(lambda a, b, m=method: knn(a, b, 1, method=m))
        comp = f.lower(q, p).compile()
        mem = comp.memory_analysis()
        if mem is not None:
            assert mem.temp_size_in_bytes < 256 * 2 ** 20
        if method == "kdtree":
            res = comp(q, p)
            sample = np.asarray(rng.choice(n, 200, replace=False))
            d_ref, _ = _reference(np.asarray(q)[sample].astype(np.float64),
                                  np.asarray(p).astype(np.float64), 1)
            np.testing.assert_allclose(np.asarray(res.distances)[sample], d_ref, rtol=1e-5)
