"""A non-finite query to the k-d tree raises: it compares false with every splitting
bound, so the search returned distance inf and an arbitrary index, silently."""

import jax
import numpy as np
import pytest

from jaxpose.geometry import build_kdtree, query_kdtree

jax.config.update("jax_enable_x64", True)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_query_raises_eagerly_and_under_jit(bad):
    pts = np.random.default_rng(0).normal(size=(64, 3))
    tree = build_kdtree(pts)
    q = np.array([[0.1, bad, 0.2], [0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"query_kdtree\(query\): contains NaN or inf"):
        query_kdtree(tree, q)
    with pytest.raises(RuntimeError, match=r"query_kdtree\(query\): contains NaN or inf"):
        jax.block_until_ready(jax.jit(lambda q: query_kdtree(tree, q))(q))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_finite_queries_still_match_brute_force(dtype):
    rng = np.random.default_rng(1)
    pts, q = rng.normal(size=(64, 3)).astype(dtype), rng.normal(size=(9, 3)).astype(dtype)
    dist, idx = jax.jit(lambda q: query_kdtree(build_kdtree(pts), q, k=2))(q)
    d2 = ((q[:, None] - pts[None]) ** 2).sum(-1)
    np.testing.assert_array_equal(idx, np.argsort(d2, 1)[:, :2])
    np.testing.assert_allclose(dist, np.sort(d2, 1)[:, :2], rtol=1e-5)
