"""Camera geometry against hand-computed values and independent numpy formulas."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxpose.geometry import (
    bal_project,
    cart2homo,
    homo2cart,
    intrinsics_matrix,
    pixel2point,
    point2pixel,
    radial_distort,
    reprojerr,
)
from jaxpose.lie import SE3

from .conftest import random_rotation, se3_from_rt

# PyPose's documented example (f = 2, 9 × 9 image): values computed by hand.
K_DOC = np.array([[2.0, 0, 4.5], [0, 2, 4.5], [0, 0, 1]])
OBJ_DOC = np.array([[2.0, 0, 2], [1, 0, 2], [0, 1, 1], [0, 0, 1], [1, 0, 1], [5, 5, 3]])


def test_homogeneous_roundtrip_and_zero_weight():
    x = np.array([[2.0, 3.0], [-1.0, 4.0]])
    h = cart2homo(x)
    np.testing.assert_array_equal(h, [[2, 3, 1], [-1, 4, 1]])
    np.testing.assert_allclose(homo2cart(h * 2.5), x)
    np.testing.assert_allclose(homo2cart(np.array([4.0, 3.0, 2.0, 1.0])), [4, 3, 2])
    # w = 0 → ±tiny, finite, sign kept
    out = homo2cart(np.array([[1.0, 0.0], [-1.0, -0.0]]))
    assert np.all(np.isfinite(out)) and out[0, 0] > 0 and out[1, 0] < 0
    g = jax.grad(lambda v: jnp.sum(homo2cart(v)))(jnp.array([1.0, 0.0]))
    assert np.all(np.isfinite(g))


def test_point2pixel_hand_values():
    # u = f x / z + c
    want = np.stack([2 * OBJ_DOC[:, 0] / OBJ_DOC[:, 2] + 4.5,
                     2 * OBJ_DOC[:, 1] / OBJ_DOC[:, 2] + 4.5], -1)
    np.testing.assert_allclose(point2pixel(OBJ_DOC, K_DOC), want, rtol=1e-14)
    np.testing.assert_allclose(want[[0, 5]], [[6.5, 4.5], [7.0 + 1 / 3 + 0.5, 7.0 + 5 / 6]],
                               rtol=1e-14)
    # with extrinsics: the example pose of PyPose's docstring (4-digit values there)
    pose = SE3(np.array([0.0, -8, 0, 0, -0.3827, 0, 0.9239])).normalize()
    px = point2pixel(OBJ_DOC, K_DOC, pose)
    np.testing.assert_allclose(np.asarray(px)[[0, 5]], [[4.4999, -1.1568], [4.9999, 3.4394]],
                               atol=2e-4)


def test_pixel2point_hand_values_and_roundtrip(rng):
    pixels = np.array([[0.5, 0.0], [1.0, 0.0], [0.0, 1.3], [5.0, 1.5]])
    depth = np.array([5.0, 3.0, 6.5, 0.7])
    pts = pixel2point(pixels, depth, K_DOC)
    np.testing.assert_allclose(pts[0], [-10.0, -11.25, 5.0], rtol=1e-14)
    np.testing.assert_allclose(pts[3], [0.175, -1.05, 0.7], rtol=1e-12)
    # skewed intrinsics and extrinsics: point2pixel ∘ pixel2point = identity
    k = intrinsics_matrix(400.0, 380.0, 320.0, 240.0, skew=3.0)
    pose = se3_from_rt(random_rotation(rng), rng.normal(size=3))
    uv = rng.uniform(0, 600, size=(2, 7, 2))
    z = rng.uniform(1, 5, size=(2, 7))
    world = pixel2point(uv, z, k, pose)
    np.testing.assert_allclose(point2pixel(world, k, pose), uv, rtol=1e-10)
    np.testing.assert_allclose(pose.act(world)[..., 2], z, rtol=1e-12)


def test_reprojerr_reductions(rng):
    pts = rng.normal(size=(3, 6, 3)) + np.array([0, 0, 6.0])
    k = intrinsics_matrix(300.0, 310.0, 100.0, 90.0)
    pix = np.asarray(point2pixel(pts, k)) + rng.normal(size=(3, 6, 2))
    d = np.asarray(point2pixel(pts, k)) - pix
    np.testing.assert_allclose(reprojerr(pts, pix, k), d)
    np.testing.assert_allclose(reprojerr(pts, pix, k, reduction="norm"), np.linalg.norm(d, axis=-1))
    np.testing.assert_allclose(reprojerr(pts, pix, k, reduction="sum"), np.abs(d).sum(-1))
    np.testing.assert_allclose(reprojerr(pts, pix, k, reduction="mean"),
                               np.linalg.norm(d, axis=-1).mean(-1))
    # zero error: the norm's derivative is 0, not NaN
    exact = point2pixel(pts, k)
    g = jax.grad(lambda p: jnp.sum(reprojerr(p, exact, k, reduction="norm")))(pts)
    assert np.all(np.isfinite(g))


def test_radial_distortion_formula(rng):
    x = rng.normal(size=(5, 2)) * 0.3
    k = np.array([0.1, -0.05, 0.01])
    r2 = (x ** 2).sum(-1, keepdims=True)
    np.testing.assert_allclose(radial_distort(x, k), x * (1 + k[0] * r2 + k[1] * r2 ** 2
                                                           + k[2] * r2 ** 3), rtol=1e-14)
    pts = rng.normal(size=(5, 3)) + np.array([0, 0, 4.0])
    kk = intrinsics_matrix(500.0, 500.0, 320.0, 240.0)
    np.testing.assert_allclose(point2pixel(pts, kk, distortion=np.zeros(2)),
                               point2pixel(pts, kk), rtol=1e-14)
    xn = pts[:, :2] / pts[:, 2:]
    want = 500 * np.asarray(radial_distort(xn, k)) + np.array([320, 240])
    np.testing.assert_allclose(point2pixel(pts, kk, distortion=k), want, rtol=1e-13)


def test_bal_model_against_numpy(rng):
    from scipy.spatial.transform import Rotation

    cams = np.concatenate([rng.normal(size=(4, 3)) * 0.3, rng.normal(size=(4, 3)),
                           rng.uniform(400, 600, (4, 1)), rng.normal(size=(4, 2)) * 0.01], -1)
    pts = rng.normal(size=(4, 3)) - np.array([0, 0, 8.0])
    pc = Rotation.from_rotvec(cams[:, :3]).apply(pts) + cams[:, 3:6]
    p = -pc[:, :2] / pc[:, 2:]
    r2 = (p ** 2).sum(-1, keepdims=True)
    want = cams[:, 6:7] * (1 + cams[:, 7:8] * r2 + cams[:, 8:9] * r2 ** 2) * p
    np.testing.assert_allclose(bal_project(pts, cams), want, rtol=1e-12)
    # broadcasting: one camera, several points
    np.testing.assert_allclose(bal_project(pts, cams[0]),
                               np.stack([bal_project(q, cams[0]) for q in pts]), rtol=1e-14)


def test_jit_vmap_grad(rng):
    k = jnp.asarray(intrinsics_matrix(300.0, 300.0, 100.0, 90.0))
    pose = se3_from_rt(random_rotation(rng, 3), rng.normal(size=(3, 3)) * 0.1)
    pts = jnp.asarray(rng.normal(size=(3, 5, 3)) + np.array([0, 0, 5.0]))

    def f(p, x, kk):
        return reprojerr(p, jnp.zeros((5, 2)), kk, SE3(x), reduction="mean",
                         distortion=jnp.array([0.01]))

    out = jax.jit(jax.vmap(f, in_axes=(0, 0, None)))(pts, pose.data, k)
    np.testing.assert_allclose(out, [f(pts[i], pose.data[i], k) for i in range(3)], rtol=1e-12)
    check_grads(jax.jit(lambda p, kk: f(p, pose.data[0], kk)), (pts[0], k), order=1,
                modes=["rev"])
    cams = jnp.asarray(np.concatenate([rng.normal(size=3) * 0.2, [0, 0, -5.0], [500.0, 0.01, 0]]))
    check_grads(jax.jit(lambda c, x: bal_project(x, c)),
                (cams, jnp.asarray(rng.normal(size=(4, 3)))), order=1, modes=["fwd", "rev"])


def test_float32_path(rng):
    pts = (rng.normal(size=(4, 3)) + np.array([0, 0, 5.0])).astype(np.float32)
    k = np.asarray(intrinsics_matrix(300.0, 300.0, 100.0, 90.0), np.float32)
    px = point2pixel(pts, k)
    assert px.dtype == jnp.float32
    back = pixel2point(px, pts[:, 2], k)
    assert back.dtype == jnp.float32
    np.testing.assert_allclose(back, pts, rtol=1e-5, atol=1e-5)


def test_bad_input_names_the_argument():
    k = np.eye(3)
    with pytest.raises(ValueError, match=r"point2pixel\(points\).*\(\.\.\., N, 3\)"):
        point2pixel(np.zeros((4, 2)), k)
    with pytest.raises(ValueError, match=r"point2pixel\(intrinsics\)"):
        point2pixel(np.zeros((4, 3)), np.eye(4))
    with pytest.raises(TypeError, match=r"point2pixel\(extrinsics\).*SE3"):
        point2pixel(np.zeros((4, 3)), k, np.zeros(7))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: points \(2,\)"):
        point2pixel(np.zeros((2, 4, 3)), np.stack([k] * 3))
    with pytest.raises(ValueError, match=r"pixel2point\(depth\)"):
        pixel2point(np.zeros((4, 2)), np.zeros(3), k)
    with pytest.raises(ValueError, match=r"reprojerr\(reduction\)"):
        reprojerr(np.zeros((4, 3)), np.zeros((4, 2)), k, reduction="l2")
    with pytest.raises(ValueError, match=r"same number of points"):
        reprojerr(np.zeros((4, 3)), np.zeros((5, 2)), k)
    with pytest.raises(ValueError, match=r"bal_project\(cameras\)"):
        bal_project(np.zeros(3), np.zeros(8))
    with pytest.raises(TypeError, match=r"homo2cart\(coordinates\)"):
        homo2cart("abc")
