"""Regressions for jaxpose.geometry: each test pins a defect that once gave a
silently wrong number (or NaN), against closed forms, finite differences or identities."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.geometry import hermite, pixel2point, point2pixel, svdtf, umeyama, voxel_filter

K = np.array([[500.0, 1.5, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])


def _central_jacobian(f, x: np.ndarray, h: float = 1e-6) -> np.ndarray:
    y = np.asarray(f(x))
    jac = np.zeros(y.shape + x.shape)
    for idx in np.ndindex(x.shape):
        e = np.zeros_like(x)
        e[idx] = h
        jac[(...,) + idx] = (np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * h)
    return jac


def test_camera_intrinsics_scale_does_not_change_pixels_or_points(rng):
    """[u, v, 1] ∝ K p: a K scaled by 2 (K₃₃ = 2) is the same camera. point2pixel with
    distortion returned 2× the pixels and pixel2point half the depth."""
    pts = rng.normal(size=(4, 3)) + [0.0, 0.0, 5.0]
    dist = np.array([0.1, -0.05])
    x = pts[:, :2] / pts[:, 2:]
    xd = x * (1 + dist[0] * np.sum(x * x, -1) + dist[1] * np.sum(x * x, -1) ** 2)[:, None]
    want = xd @ K[:2, :2].T + K[:2, 2]
    np.testing.assert_allclose(point2pixel(pts, 2 * K, distortion=dist), want, rtol=1e-12)
    px = pts[:, :2] / pts[:, 2:] @ K[:2, :2].T + K[:2, 2]  # no distortion
    np.testing.assert_allclose(pixel2point(px, pts[:, 2], 2 * K), pts, rtol=1e-12)


def test_registration_derivative_finite_for_coincident_source(rng):
    """Coincident source points (a single point, documented as a pure translation): the
    derivative was NaN (0/0 in the rotation's JVP) instead of FD's −R/N."""
    src = np.tile(rng.normal(size=3), (2, 1))
    tgt = src + [1.0, -2.0, 0.5]
    f = jax.jit(lambda s: svdtf(s, tgt).data)
    jac = np.asarray(jax.jacfwd(f)(src))
    np.testing.assert_allclose(jac, _central_jacobian(f, src), atol=1e-8)
    g = jax.jit(lambda s: umeyama(s, tgt).data)
    jac = np.asarray(jax.jacfwd(g)(src))
    np.testing.assert_allclose(jac, _central_jacobian(g, src), atol=1e-8)


def test_registration_rejects_negative_weights(rng):
    """Weights must be non-negative; mixed signs gave an arbitrary transform."""
    s, t = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    w = np.array([1.0, 1.0, -1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match=r"svdtf\(weights\).*non-negative"):
        svdtf(s, t, w)
    with pytest.raises(RuntimeError, match=r"umeyama\(weights\).*non-negative"):
        jax.block_until_ready(jax.jit(lambda w: umeyama(s, t, weights=w).data)(w))


def test_hermite_rejects_non_increasing_times(rng):
    """Repeated knots gave ±inf, unsorted knots a wrong finite curve."""
    p = rng.normal(size=(5, 2))
    for times in ([0.0, 1.0, 1.0, 2.0, 3.0], [0.0, 2.0, 1.0, 3.0, 4.0]):
        with pytest.raises(ValueError, match=r"hermite\(times\).*increasing"):
            hermite(p, [0.5], times=times)
    with pytest.raises(RuntimeError, match=r"hermite\(times\).*increasing"):
        jax.block_until_ready(jax.jit(lambda tk: hermite(p, [0.5], times=tk))(
            jnp.asarray([0.0, 1.0, 1.0, 2.0, 3.0])))


def test_voxel_filter_rejects_voxel_indices_beyond_int32():
    """Voxel indices beyond 2³¹ saturated, merging distinct voxels (4 points 1e3 apart
    with a 1e-7 voxel came back as 2 voxels); non-positive sizes passed under jit."""
    pts = np.array([[0.0, 0.0, 0.0], [1e3, 0.0, 0.0], [2e3, 0.0, 0.0], [5e3, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"voxel_filter\(voxel\).*small"):
        voxel_filter(pts, np.array([1e-7, 1.0, 1.0]))
    f = jax.jit(lambda v: voxel_filter(pts, v, max_voxels=4).points)
    with pytest.raises(RuntimeError, match=r"voxel_filter\(voxel\).*positive"):
        jax.block_until_ready(f(jnp.array([-1.0, 1.0, 1.0])))
    np.testing.assert_allclose(f(jnp.array([1.0, 1.0, 1.0])), pts)


def test_shape_errors_name_the_argument(rng):
    """Wrong-length ``hint`` / ``valid`` gave reshape/broadcast errors naming nothing."""
    from jaxpose.geometry import build_kdtree, error_stats, query_kdtree

    tree = build_kdtree(rng.normal(size=(10, 3)))
    with pytest.raises(ValueError, match=r"query_kdtree\(hint\).*\(4,\)"):
        query_kdtree(tree, rng.normal(size=(4, 3)), 1, hint=np.array([1, 2, 3]))
    with pytest.raises(ValueError, match=r"error_stats\(valid\)"):
        error_stats(np.ones(4), np.ones(5, bool))
    from jaxpose.geometry import associate, estimate_normals
    from jaxpose.lie import InvalidValueError

    with pytest.raises(ValueError, match=r"estimate_normals\(viewpoint\)"):
        estimate_normals(rng.normal(size=(6, 3)), 3, viewpoint=np.zeros(2))
    with pytest.raises(InvalidValueError, match=r"associate\(ref_stamps\).*ascending"):
        associate(np.array([0.0, 2.0, 1.0]), np.array([0.0, 1.0, 2.0]))
