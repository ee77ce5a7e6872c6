"""Kabsch / Umeyama: exact on noise-free data (reflection cases included), optimal on
mirrored data against a brute-force search, gradients against finite differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxpose.geometry import svdstf, svdtf, umeyama
from jaxpose.geometry._registration import optimal_rotation
from jaxpose.lie import SE3

from .conftest import random_rotation

svdtf_j = jax.jit(lambda s, t: svdtf(s, t).matrix())
umeyama_j = jax.jit(lambda s, t, w: umeyama(s, t, weights=w).matrix())


def _numpy_kabsch(src: np.ndarray, tgt: np.ndarray) -> np.ndarray:
    """Reference: textbook Kabsch in numpy (4 × 4)."""
    cs, ct = src.mean(0), tgt.mean(0)
    u, _, vt = np.linalg.svd((tgt - ct).T @ (src - cs))
    d = np.sign(np.linalg.det(u @ vt))
    r = u @ np.diag([1, 1, d]) @ vt
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, ct - r @ cs
    return m


def test_kabsch_exact_batched(rng):
    r = random_rotation(rng, 5)
    t = rng.normal(size=(5, 3))
    src = rng.normal(size=(5, 30, 3))
    tgt = np.einsum("bij,bnj->bni", r, src) + t[:, None]
    m = np.asarray(svdtf_j(src, tgt))
    np.testing.assert_allclose(m[:, :3, :3], r, atol=1e-13)
    np.testing.assert_allclose(m[:, :3, 3], t, atol=1e-13)
    np.testing.assert_allclose(m[0], _numpy_kabsch(src[0], tgt[0]), atol=1e-13)


@pytest.mark.parametrize("kind", ["coplanar", "three_points", "collinear"])
def test_kabsch_exact_in_reflection_prone_configurations(rng, kind):
    """Coplanar / minimal sets: det(U Vᵀ) can be −1 for the naive SVD; the fix must
    return the proper rotation and reproduce the target exactly."""
    r = random_rotation(rng)
    t = rng.normal(size=3)
    if kind == "coplanar":
        src = np.concatenate([rng.normal(size=(12, 2)), np.zeros((12, 1))], -1)
    elif kind == "three_points":
        src = rng.normal(size=(3, 3))
    else:  # rotation about the line is free; any minimiser maps source onto target
        src = np.linspace(-1, 1, 6)[:, None] * np.array([1.0, 2.0, -0.5])
    tgt = src @ r.T + t
    m = np.asarray(svdtf_j(src, tgt))
    np.testing.assert_allclose(np.linalg.det(m[:3, :3]), 1.0, atol=1e-12)
    np.testing.assert_allclose(src @ m[:3, :3].T + m[:3, 3], tgt, atol=1e-12)
    if kind != "collinear":
        np.testing.assert_allclose(m[:3, :3], r, atol=1e-12)


def test_kabsch_on_mirror_image_is_the_best_proper_rotation(rng):
    """Target = reflection of the source: no rotation fits; the result must be a proper
    rotation whose cost equals the brute-force minimum over SO(3)."""
    from scipy.optimize import minimize
    from scipy.spatial.transform import Rotation

    src = rng.normal(size=(15, 3)) * np.array([3.0, 2.0, 1.0])
    tgt = src * np.array([1.0, 1.0, -1.0]) + np.array([0.5, -1.0, 2.0])
    m = np.asarray(svdtf_j(src, tgt))
    assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    cost = lambda r, t: np.sum((src @ r.T + t - tgt) ** 2)
    ours = cost(m[:3, :3], m[:3, 3])

    def f(v):
        rot = Rotation.from_rotvec(v[:3]).as_matrix()
        return cost(rot, v[3:])

    best = min(minimize(f, np.concatenate([rng.normal(size=3), np.zeros(3)]), method="BFGS",
                        options={"gtol": 1e-10}).fun for _ in range(8))
    assert ours <= best + 1e-8
    assert ours == pytest.approx(best, rel=1e-8)


def test_umeyama_exact_and_weights(rng):
    r = random_rotation(rng)
    t, s = rng.normal(size=3), 2.7
    src = rng.normal(size=(20, 3))
    tgt = s * src @ r.T + t
    w = np.ones(20)
    m = np.asarray(umeyama_j(src, tgt, w))
    np.testing.assert_allclose(m[:3, :3], s * r, atol=1e-12)
    np.testing.assert_allclose(m[:3, 3], t, atol=1e-12)
    # zero-weight outliers are ignored
    bad = tgt.copy()
    bad[:4] += 10 * rng.normal(size=(4, 3))
    w[:4] = 0
    np.testing.assert_allclose(np.asarray(umeyama_j(src, bad, w)), m, atol=1e-11)
    # with_scale=False equals Kabsch; PyPose's name
    np.testing.assert_allclose(umeyama(src, tgt, with_scale=False).matrix(),
                               svdtf(src, tgt).matrix(), atol=1e-12)
    assert svdstf(src, tgt).scale() == pytest.approx(s, rel=1e-12)
    # reflection: proper rotation and s > 0
    mir = umeyama(src, src * np.array([-1.0, 1, 1]))
    assert np.linalg.det(mir.rotation().matrix()) == pytest.approx(1.0, abs=1e-12)
    assert mir.scale() > 0


@pytest.mark.slow
def test_rotation_second_derivatives(rng):
    h = jnp.asarray(rng.normal(size=(3, 3)))
    check_grads(jax.jit(optimal_rotation), (h,), order=2, modes=["fwd", "rev"], atol=1e-6,
                rtol=1e-6)


def test_rotation_derivative_custom_jvp(rng):
    h = jnp.asarray(rng.normal(size=(3, 3)))
    check_grads(jax.jit(optimal_rotation), (h,), order=1, modes=["fwd", "rev"], atol=1e-6,
                rtol=1e-6)
    # symmetric cloud (equal singular values): SVD derivatives are undefined, ours are not
    cube = np.stack(np.meshgrid(*[[-1.0, 1.0]] * 3), -1).reshape(-1, 3)
    pose = SE3.exp(jnp.array([0.1, 0.2, 0.3, 0.3, -0.2, 0.1]))
    tgt = pose.act(cube)
    g = jax.jit(jax.grad(lambda s: jnp.sum(svdtf(s, tgt).data)))(jnp.asarray(cube))
    assert np.all(np.isfinite(g))
    check_grads(jax.jit(lambda s: svdtf(s, tgt).data), (jnp.asarray(cube),), order=1,
                modes=["rev"], atol=1e-6, rtol=1e-6)


def test_vmap_matches_batch_and_float32(rng):
    src = rng.normal(size=(4, 10, 3))
    tgt = src @ random_rotation(rng).T + 1.0
    batched = svdtf_j(src, tgt)
    mapped = jax.vmap(svdtf_j)(src, tgt)
    np.testing.assert_allclose(mapped, batched, atol=1e-13)
    m32 = svdtf(src[0].astype(np.float32), tgt[0].astype(np.float32))
    assert m32.dtype == jnp.float32
    np.testing.assert_allclose(m32.matrix(), batched[0], atol=1e-5)


def test_bad_input():
    with pytest.raises(ValueError, match=r"svdtf\(source\) and svdtf\(target\).*same number"):
        svdtf(np.zeros((5, 3)), np.zeros((6, 3)))
    with pytest.raises(ValueError, match=r"svdtf\(source\).*empty"):
        svdtf(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"umeyama\(target\).*\(\.\.\., N, 3\)"):
        umeyama(np.zeros((5, 3)), np.zeros((5, 2)))
    with pytest.raises(ValueError, match=r"umeyama\(weights\)"):
        umeyama(np.zeros((5, 3)), np.zeros((5, 3)), weights=np.ones(4))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: source"):
        svdtf(np.zeros((2, 5, 3)), np.zeros((3, 5, 3)))


def _numpy_optimal_rotation(h: np.ndarray) -> np.ndarray:
    """Reference: argmax tr(Rᵀ H) over SO(3) by NumPy's SVD with the reflection fix."""
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ (np.diag([1.0, 1.0, 1.0])[None] * np.stack([np.ones_like(d), np.ones_like(d),
                                                            d], -1)[:, None, :]) @ vt


def _with_condition(rng, kappa: float, det_sign: float = 1.0) -> np.ndarray:
    u, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    v, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    h = u @ np.diag([1.0, kappa ** -0.5, 1.0 / kappa]) @ v.T
    return h if np.sign(np.linalg.det(h)) == det_sign else h * np.array([1.0, 1.0, -1.0])


def test_optimal_rotation_newton_and_svd_paths_match_numpy(rng):
    from jaxpose.geometry._registration import _polar_rotation

    hs = np.concatenate([
        rng.normal(size=(64, 3, 3)),                               # half with det < 0
        np.stack([_with_condition(rng, k) for k in (1e2, 1e5, 1e8, 1e12)]),
        np.stack([_with_condition(rng, 1e3, -1.0)]),               # a reflection
        np.stack([np.outer(rng.normal(size=3), rng.normal(size=3))  # rank 1
                  + np.outer(rng.normal(size=3), rng.normal(size=3))]),  # rank 2: det 0
        np.zeros((1, 3, 3)),
    ])
    r = np.asarray(jax.jit(optimal_rotation)(hs))
    want = _numpy_optimal_rotation(hs)
    np.testing.assert_allclose(r[:-1], want[:-1], atol=1e-11)  # the zero matrix: any R
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape),
                               atol=1e-12)
    # which lanes Newton's iteration takes: det > 0 and converged; the SVD the others
    _, ok = _polar_rotation(jnp.asarray(hs))
    ok = np.asarray(ok)
    assert np.all(ok[np.linalg.det(hs) <= 0] == False)  # noqa: E712
    assert np.all(ok[64:67]) and np.mean(ok[:64]) > 0.3
    assert not ok[67]  # κ = 1e12, σ₂σ₃ = 1e-18 < eps: below the gate (POLAR_MIN_DET)
    # a lane's rotation does not depend on its neighbours' path (vmap = batch = single, to
    # rounding: XLA vectorises a batch differently)
    one = jax.jit(optimal_rotation)
    single = np.stack([np.asarray(one(jnp.asarray(h))) for h in hs])
    np.testing.assert_allclose(single[:-1], r[:-1], rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(jax.jit(jax.vmap(optimal_rotation))(hs))[:-1],
                               r[:-1], rtol=0, atol=1e-14)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_optimal_rotation_of_nearly_collinear_clouds(rng, dtype):
    """Two tiny singular values (nearly collinear points): cof(H), Newton's first inverse,
    is rounding noise in its smallest direction, and the iteration converged — checked as
    orthogonal, det +1 — to an O(1) wrong rotation (σ = (1, 1e-10, 1e-10): error 1.8; a
    collinear cloud's T·source missed the target in 59 of 100 draws). Those H go to the
    SVD; the rotation about the line still maps the points exactly."""
    from jaxpose.geometry._registration import _polar_rotation

    eps = np.finfo(dtype).eps
    for s2, s3 in ((1e-10, 1e-10), (1e-12, 1e-12), (1e-8, 1e-16), (1e-4, 1e-8), (1e-6, 1e-6)):
        u, v = random_rotation(rng, 2)
        h = u @ np.diag([1.0, s2, s3]) @ v.T
        want = u @ v.T  # det H > 0: the polar factor, computed in float64
        r = np.asarray(jax.jit(optimal_rotation)(h.astype(dtype)), np.float64)
        # the SVD's own error, ~eps·σ₁/(σ₂ + σ₃)
        assert np.abs(r - want).max() <= max(1e-6, 10 * eps / (s2 + s3)), (s2, s3)
        if s2 * s3 < eps:
            assert not bool(_polar_rotation(jnp.asarray(h.astype(dtype)))[1])
    # collinear clouds: a minimiser, T·source = target (rotations about the line are free)
    for _ in range(20):
        direction = rng.normal(size=3)
        src = rng.normal(size=(12, 1)) * direction + rng.normal(size=3)
        rot = random_rotation(rng, 1)[0]
        tgt = src @ rot.T + rng.normal(size=3)
        m = np.asarray(svdtf_j(src.astype(dtype), tgt.astype(dtype)), np.float64)
        moved = src @ m[:3, :3].T + m[:3, 3]
        assert np.sqrt(np.mean((moved - tgt) ** 2)) <= 1e4 * eps * np.abs(tgt).max()


def test_optimal_rotation_float32(rng):
    h = rng.normal(size=(200, 3, 3)).astype(np.float32)
    r = np.asarray(jax.jit(optimal_rotation)(h))
    assert r.dtype == np.float32
    want = _numpy_optimal_rotation(h.astype(np.float64))
    # float32 rotations where the SVD's gap is not tiny (σ₂ + σ₃ ≥ 0.1·σ₁)
    s = np.linalg.svd(h.astype(np.float64), compute_uv=False)
    fine = s[:, 1] + s[:, 2] * np.sign(np.linalg.det(h)) >= 0.1 * s[:, 0]
    np.testing.assert_allclose(r[fine], want[fine], atol=2e-5)
