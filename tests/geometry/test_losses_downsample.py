"""Geodesic loss against closed forms; voxel / random down-sampling against numpy."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.geometry import geodesic_loss, random_filter, voxel_filter
from jaxpose.lie import SE3, SO3, Sim3, se3, so3

from .conftest import pypose


def test_geodesic_loss_closed_form_and_types():
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    angles = np.array([0.0, 0.5, 2.0, np.pi - 1e-6])
    x = SO3.exp(jnp.asarray(angles[:, None] * axis))
    y = SO3.identity((4,))
    np.testing.assert_allclose(geodesic_loss(x, y, "none"), angles, atol=1e-12)
    assert float(geodesic_loss(x, y)) == pytest.approx(angles.mean())
    assert float(geodesic_loss(x, y, "sum")) == pytest.approx(angles.sum())
    # rotation parts of other groups and algebra elements
    t = SE3(jnp.concatenate([jnp.ones((4, 3)), x.data], -1))
    s = Sim3(jnp.concatenate([jnp.ones((4, 3)), x.data, 2 * jnp.ones((4, 1))], -1))
    np.testing.assert_allclose(geodesic_loss(t, s, "none"), 0.0, atol=1e-12)
    a = so3(jnp.asarray(angles[1:2, None] * axis))
    assert float(geodesic_loss(a, se3(jnp.zeros(6)))) == pytest.approx(0.5)
    # derivative at θ = 0 is 0 (not NaN); d θ / d φ = unit axis elsewhere
    g = jax.jit(jax.grad(lambda v: geodesic_loss(SO3.exp(v), SO3.identity())))
    np.testing.assert_array_equal(g(jnp.zeros(3)), 0.0)
    np.testing.assert_allclose(g(jnp.asarray(0.7 * axis)), axis, atol=1e-12)
    vm = jax.vmap(lambda p, q: geodesic_loss(SO3(p), SO3(q)))(x.data, y.data)
    np.testing.assert_allclose(vm, angles, atol=1e-12)
    with pytest.raises(TypeError, match=r"geodesic_loss\(target\)"):
        geodesic_loss(x, np.zeros(4))
    with pytest.raises(ValueError, match=r"geodesic_loss\(reduction\)"):
        geodesic_loss(x, y, "max")


def test_voxel_filter_centroids_and_random(rng):
    pts = rng.uniform(0, 10, (300, 4))
    size = np.array([2.0, 2.5, 3.0])
    out = voxel_filter(pts, size)
    # numpy reference: group by voxel index, centroid, lexicographic order
    cells = np.floor((pts[:, :3] - pts[:, :3].min(0)) / size).astype(int)
    keys, inv = np.unique(cells, axis=0, return_inverse=True)
    want = np.stack([pts[inv.ravel() == i].mean(0) for i in range(len(keys))])
    assert int(out.count) == len(keys) and out.points.shape == want.shape
    np.testing.assert_allclose(out.points, want, rtol=1e-12)
    # jit with a capacity (smaller than the count: overflow reported, rest dropped)
    f = jax.jit(lambda p, k: voxel_filter(p, size, max_voxels=40, key=k))
    small = f(pts, jax.random.PRNGKey(1))
    assert int(small.count) == len(keys) and int(np.sum(small.valid)) == 40
    chosen = np.asarray(small.points)
    for i in range(40):  # each pick is a member of its voxel
        members = pts[inv.ravel() == i]
        assert np.any(np.all(members == chosen[i], axis=-1))
    with pytest.raises(TypeError, match=r"voxel_filter\(max_voxels\)"):
        jax.jit(lambda p: voxel_filter(p, size))(pts)
    with pytest.raises(ValueError, match=r"voxel_filter\(voxel\).*positive"):
        voxel_filter(pts, np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match=r"voxel_filter\(points\).*empty"):
        voxel_filter(np.zeros((0, 3)), size)
    # gradient of the centroids
    g = jax.grad(lambda p: jnp.sum(voxel_filter(p, size, max_voxels=60).points))(pts)
    np.testing.assert_allclose(np.asarray(g).sum(), 4 * min(60, len(keys)), rtol=1e-12)


def test_random_filter(rng):
    pts = rng.normal(size=(2, 50, 3))
    out = random_filter(pts, 10, jax.random.PRNGKey(0))
    assert out.shape == (2, 10, 3)
    idx = [int(np.argmin(np.abs(pts[0] - o).sum(-1))) for o in np.asarray(out[0])]
    assert len(set(idx)) == 10  # distinct points
    np.testing.assert_array_equal(out[1], pts[1][idx])  # same draw for every batch
    with pytest.raises(ValueError, match=r"random_filter\(num\)"):
        random_filter(pts, 51, jax.random.PRNGKey(0))


@pytest.mark.peer
def test_pypose_voxel_parity(rng):
    pp = pypose()
    import torch

    pts = rng.uniform(0, 10, (200, 3))
    ours = voxel_filter(pts, np.array([2.0, 2.0, 2.0]))
    np.testing.assert_allclose(ours.points, pp.voxel_filter(torch.tensor(pts), [2.0, 2, 2]),
                               rtol=1e-12)
    a, b = SO3.random(jax.random.PRNGKey(0), (5,)), SO3.random(jax.random.PRNGKey(1), (5,))
    want = pp.geodesic_loss(pp.SO3(torch.tensor(np.asarray(a.data))),
                            pp.SO3(torch.tensor(np.asarray(b.data))))
    assert float(geodesic_loss(a, b)) == pytest.approx(float(want), rel=1e-10)
