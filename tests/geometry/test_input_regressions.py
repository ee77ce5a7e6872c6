"""Regressions for jaxpose.geometry: each test pins a defect that once gave a
silently wrong number (or NaN), against closed forms, finite differences or identities."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.geometry import hermite, pixel2point, point2pixel, svdtf, umeyama, voxel_filter
from jaxpose.lie import SO3

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


# Found by an audit (session 48)
def test_kabsch_reverse_mode_with_coincident_points_is_finite(rng):
    """With a zero cross-covariance (coincident source or target points, one point) the
    rotation's tangent is 0, and forward mode gave it; reverse mode divided the cotangent
    by the tiny scale first (inf) and then multiplied by 0: an all-NaN gradient. The
    translation is c_t − R·c_s, so d/ds Σ t = −(1/N)·Σ_rows R: forward mode is the
    reference, and it is finite."""
    tgt = jnp.asarray(rng.normal(size=(4, 3)))
    same = jnp.ones((4, 3))
    f = lambda s: svdtf(s, tgt).data.sum()  # noqa: E731
    np.testing.assert_allclose(jax.grad(f)(same), jax.jacfwd(f)(same), atol=1e-12)
    g = lambda t: svdtf(tgt, t).data.sum()  # noqa: E731
    np.testing.assert_allclose(jax.grad(g)(same), jax.jacfwd(g)(same), atol=1e-12)
    u = lambda s: umeyama(s, tgt[:1]).data.sum()  # noqa: E731
    np.testing.assert_allclose(jax.grad(u)(same[:1]), jax.jacfwd(u)(same[:1]), atol=1e-12)
    # a regular configuration keeps its derivative (central differences)
    src = jnp.asarray(rng.normal(size=(4, 3)))
    np.testing.assert_allclose(jax.grad(f)(src), _central_jacobian(f, np.asarray(src)),
                               rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("skew, n", [(1.5, 5), (0.0, 6)])
def test_epnp_on_finite_collinear_points_is_degenerate(skew, n):
    """On a line every candidate pose could fail the Z > 0 test (all errors inf), and the
    status said NON_FINITE for finite input; the documented status is DEGENERATE."""
    from jaxpose.geometry import epnp
    from jaxpose.lie import SE3
    from jaxpose.results import Results

    cam = np.array([[500.0, skew, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
    pose = SE3.exp(jnp.array([0.1, -0.2, 4.0, 0.3, -0.2, 0.5]))
    pw = np.outer(np.arange(1.0, n + 1), [1.0, 2.0, 3.0]) * 0.1
    px = np.asarray(point2pixel(pw, cam, pose))
    for refine in (False, True):
        assert int(epnp(pw, px, cam, refine=refine).status) == Results.DEGENERATE
    bad = px.copy()
    bad[0, 0] = np.nan
    assert int(epnp(pw, bad, cam).status) == Results.NON_FINITE


@pytest.mark.parametrize("method", ["brute", "kdtree"])
def test_knn_refuses_a_nan_query_with_either_method(method):
    """Brute force returned a NaN distance and an arbitrary index where the k-d tree
    raised, and method='auto' picks between them by problem size."""
    from jaxpose.geometry import knn

    pts = np.arange(12.0).reshape(4, 3)
    q = np.array([[0.0, 1.0, 2.0], [np.nan, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"knn\(query\): contains NaN or inf"):
        knn(q, pts, method=method)
    with pytest.raises(RuntimeError, match=r"knn\(query\): contains NaN or inf"):
        jax.block_until_ready(jax.jit(lambda a: knn(a, pts, method=method).indices)(q))
    assert int(knn(q[:1], pts, method=method).indices[0, 0]) == 0


# Found by an audit (session 49): value checks that ran on known values only
# ----------------------------------------------------------------------------------
def test_icp_max_distance_is_checked_under_jit_and_vmap(rng):
    """A traced max_distance skipped the check: −0.2 was squared into the gate and the
    result (status converged) was that of +0.2; NaN gave status degenerate."""
    from jaxpose.geometry import icp

    src = rng.normal(size=(30, 3))
    tgt = src + 0.05
    message = r"icp\(max_distance\): expected a positive number"
    fitness = jax.jit(lambda md: icp(src, tgt, max_distance=md).fitness)
    for bad in (-0.2, float("nan")):
        with pytest.raises(ValueError, match=message):
            icp(src, tgt, max_distance=bad)
        with pytest.raises(Exception, match=message):
            jax.block_until_ready(fitness(bad))
    with pytest.raises(Exception, match=message):
        jax.block_until_ready(jax.vmap(fitness)(jnp.array([0.2, -0.2])))
    good = jax.jit(lambda md: icp(src, tgt, max_distance=md))(0.2)
    np.testing.assert_allclose(good.transform.translation(), [0.05] * 3, atol=1e-9)


@pytest.mark.parametrize("name", ["nbr_filter", "knn_filter"])
@pytest.mark.parametrize("bad", [-1.0, float("nan")])
def test_radius_filter_radius_is_checked_under_jit(rng, name, bad):
    """A traced negative or NaN radius removed every point (count 0) without an error."""
    from jaxpose import geometry

    pts = rng.normal(size=(50, 3))
    fn = getattr(geometry, name)
    with pytest.raises(ValueError, match=rf"{name}\(radius\): expected a non-negative radius"):
        fn(pts, 3, bad)
    with pytest.raises(Exception, match=rf"{name}\(radius\): expected a non-negative radius"):
        jax.block_until_ready(jax.jit(lambda r: fn(pts, 3, r).count)(bad))
    kept = jax.jit(lambda r: fn(pts, 3, r).count)(10.0)
    assert int(kept) == 50


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_voxel_filter_refuses_non_finite_coordinates(bad):
    """One NaN point made the grid origin NaN: the finite points x = 0, 0.05, 0.5 came
    back as one voxel with a NaN centroid (three voxels: 0.025, 0.5, 1). inf blamed the
    voxel size. Extra columns (colours) are averaged, NaN or not."""
    pts = np.array([[0.0, 0, 0], [0.05, 0, 0], [0.5, 0, 0], [1, 1, 1], [bad, 0, 0]])
    message = r"voxel_filter\(points\): the voxelised coordinates contain NaN or inf"
    with pytest.raises(ValueError, match=message):
        voxel_filter(pts, np.full(3, 0.1))
    with pytest.raises(Exception, match=message):
        jax.block_until_ready(jax.jit(voxel_filter, static_argnums=2)(pts, np.full(3, 0.1), 8))
    out = voxel_filter(pts[:4], np.full(3, 0.1))
    np.testing.assert_allclose(np.asarray(out.points)[:, 0], [0.025, 0.5, 1.0])
    colour = np.c_[pts[:4], [np.nan, 1.0, 2.0, 3.0]]
    out = voxel_filter(colour, np.full(3, 0.1))
    assert np.isnan(np.asarray(out.points)[0, 3]) and int(out.count) == 3


def test_bal_project_is_not_finite_at_depth_zero():
    """The BAL model divides by the depth: a point at the camera centre gave pixels
    (−0, −0) and one at (1e-300, 0, 0) gave (−2.2e10, 0) (homo2cart's ±tiny), where the
    BAL solver's residual and the NumPy model give NaN."""
    from jaxpose.geometry import bal_project

    cam = np.array([0.0, 0, 0, 0, 0, 0, 500.0, 0.0, 0.0])
    for x in ([0.0, 0, 0], [1e-300, 0, 0], [1.0, 2.0, 0.0]):
        assert not np.all(np.isfinite(np.asarray(bal_project(np.array(x), cam))))
    np.testing.assert_allclose(bal_project(np.array([1.0, 2.0, -4.0]), cam), [125.0, 250.0])


def test_umeyama_float32_far_from_the_origin():
    """A 500-pose float32 random walk 1e5–2e5 from the origin: the centroids were one
    weighted sum, up to 0.2 off, which inflated the source variance and biased the scale
    (APE with align="sim3" 0.56 against 0.03 on such a walk). A second pass over the
    deviations fixes them; reference: the same float32 data solved in float64."""
    rng = np.random.default_rng(0)
    dst = np.cumsum(rng.normal(size=(500, 3)), 0) + [1e5, 2e5, 0.0]
    rot = np.asarray(SO3.exp(jnp.array([0.1, 0.2, -0.3])).matrix())
    src = (dst - [0.5, -1.0, 2.0]) @ rot / 1.7 + 0.01 * rng.normal(size=(500, 3))
    src32, dst32 = src.astype(np.float32), dst.astype(np.float32)
    want = umeyama(src32.astype(np.float64), dst32.astype(np.float64))
    got = umeyama(src32, dst32)
    assert got.data.dtype == jnp.float32
    assert abs(float(got.scale()) / float(want.scale()) - 1) < 2e-5


def test_pypose_splines_in_float32_on_long_inputs():
    """chspline / bspline built their sample times i + k·interval in float64 and cast them
    to float32 before splitting them into segment and fraction: at t ≈ 2e4 float32's
    spacing is 2e-3, so N = 20 000 points were 3.6e-3 (chspline) and 2.2e-2 (bspline
    translation) off the float64 result, against ~1e-5 from rounding the values (here
    N = 5 000: spacing 5e-4)."""
    from jaxpose.geometry import bspline, chspline
    from jaxpose.lie import SE3, se3

    rng = np.random.default_rng(0)
    n = 5_000
    pts = np.cumsum(rng.normal(size=(n, 3)), 0)
    want = np.asarray(chspline(pts, 0.1))
    got = chspline(pts.astype(np.float32), 0.1)
    assert got.dtype == jnp.float32 and got.shape == want.shape == (10 * (n - 1) + 1, 3)
    assert np.abs(np.asarray(got, np.float64) - want).max() < 2e-4
    tw = np.c_[np.cumsum(rng.normal(size=(n, 3)), 0), 0.1 * rng.normal(size=(n, 3))]
    poses = se3(jnp.asarray(tw)).exp()
    want = np.asarray(bspline(poses, 0.1).data)
    got = np.asarray(bspline(SE3(poses.data.astype(jnp.float32)), 0.1).data, np.float64)
    assert np.abs(got[:, :3] - want[:, :3]).max() < 2e-4
