"""EPnP: exact on noise-free data (general and planar), within noise on noisy data
against a brute-force least-squares reference, statuses, derivatives."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose import Results
from jaxpose.geometry import epnp, intrinsics_matrix, point2pixel
from jaxpose.lie import SE3

from .conftest import random_rotation, se3_from_rt

K = np.array([[520.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
N = 12

epnp_plain = jax.jit(lambda p, u, k: epnp(p, u, k, refine=False))
epnp_refined = jax.jit(lambda p, u, k: epnp(p, u, k, refine=True, refine_steps=20))


def _scene(rng: np.random.Generator, batch: int, planar: bool = False):
    """World points in a 2 m box and camera poses looking at it from 4–6 m."""
    pw = rng.uniform(-1, 1, size=(batch, N, 3))
    if planar:
        pw[..., 2] = 0.0
    r = random_rotation(rng, batch)
    t = np.c_[rng.normal(size=(batch, 2)) * 0.3, rng.uniform(4, 6, batch)]
    pose = se3_from_rt(r, t)
    return pw, pose, np.asarray(point2pixel(pw, K, pose))


def _rot_err(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    r = np.einsum("...ji,...jk->...ik", a[..., :3, :3], b[..., :3, :3])
    return np.arccos(np.clip((np.trace(r, axis1=-2, axis2=-1) - 1) / 2, -1, 1))


def test_exact_on_noise_free_data_with_status_cases(rng):
    """One batch: 4 general scenes, 2 planar scenes, a collinear one, one with NaN."""
    pw, pose, uv = _scene(rng, 4)
    pp_, pose_p, uv_p = _scene(rng, 2, planar=True)
    line = np.linspace(-1, 1, N)[:, None] * np.array([1.0, 0.5, 0.2])
    uv_line = np.asarray(point2pixel(line, K, pose[0]))
    bad_uv = uv[0].copy()
    bad_uv[2, 0] = np.nan
    pts = np.concatenate([pw, pp_, line[None], pw[:1]])
    pix = np.concatenate([uv, uv_p, uv_line[None], bad_uv[None]])
    res = epnp_plain(pts, pix, K)
    status = np.asarray(res.status)
    np.testing.assert_array_equal(status[:6], Results.CONVERGED)
    assert status[6] == Results.DEGENERATE and status[7] == Results.NON_FINITE
    want = np.concatenate([pose.matrix(), pose_p.matrix()])
    got = np.asarray(res.transform.matrix())[:6]
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert np.all(np.asarray(res.error)[:6] < 1e-8)
    assert np.all(np.isfinite(np.asarray(res.transform.data)))


def _brute_force_ls(pw, uv, k, starts):
    """Reference optimum of Σ |π(K, T p) − u|² by scipy least squares from several
    starting poses (rotation vector + translation), independent of jaxpose."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def res(x):
        pc = Rotation.from_rotvec(x[:3]).apply(pw) + x[3:]
        h = pc @ k.T
        return (h[:, :2] / h[:, 2:] - uv).ravel()

    best = None
    for x0 in starts:
        sol = least_squares(res, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15, method="lm")
        if best is None or sol.cost < best.cost:
            best = sol
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(best.x[:3]).as_matrix()
    m[:3, 3] = best.x[3:]
    return m, best.cost


def test_noisy_data_within_noise_of_brute_force_optimum(rng):
    from scipy.spatial.transform import Rotation

    pw, pose, uv = _scene(rng, 3)
    sigma = 1.0  # pixels
    noisy = uv + rng.normal(size=uv.shape) * sigma
    refined = epnp_refined(pw, noisy, K)
    plain = epnp_plain(pw, noisy, K)
    truth = np.asarray(pose.matrix())
    for b in range(3):
        starts = [np.r_[Rotation.from_matrix(truth[b, :3, :3]).as_rotvec(), truth[b, :3, 3]]]
        starts += [np.r_[rng.normal(size=3) * 0.3, 0, 0, 5.0] for _ in range(3)]
        ref, _ = _brute_force_ls(pw[b], noisy[b], K, starts)
        # the refined pose is the least-squares optimum
        np.testing.assert_allclose(np.asarray(refined.transform.matrix())[b], ref, atol=1e-7)
        # the closed-form pose is within the noise of it: ~σ/f rad, ~σ/f · depth m
        p = np.asarray(plain.transform.matrix())[b]
        assert _rot_err(p, ref) < 5 * sigma / 500 * 3
        assert np.linalg.norm(p[:3, 3] - ref[:3, 3]) < 5 * sigma / 500 * 6 * 3
        # and its squared reprojection error (what it minimises; ``error`` is the mean of
        # the unsquared ones, which the optimum need not lower) is at most the closed form's
        assert _squared_error(pw[b], noisy[b], ref) <= _squared_error(pw[b], noisy[b], p) + 1e-9


def _squared_error(pw, uv, m):
    """Σ‖project(m·p) − uv‖² in pixels² (numpy)."""
    cam = pw @ m[:3, :3].T + m[:3, 3]
    h = cam @ K.T
    return float(np.sum((h[:, :2] / h[:, 2:] - uv) ** 2))


def _tangent_gradient(pw, uv, t):
    """‖∇_δ ½Σ‖project(T·Exp(δ)·p) − uv‖²‖∞ at δ = 0 (autodiff of the plain projection,
    independent of epnp's hand-written Jacobian)."""
    def cost(delta):
        h = SE3(jnp.asarray(t)).retract(delta).act(jnp.asarray(pw)) @ K.T
        return 0.5 * jnp.sum((h[:, :2] / h[:, 2:] - uv) ** 2)

    return float(jnp.max(jnp.abs(jax.grad(cost)(jnp.zeros(6)))))


def test_jit_vmap_grad_implicit_derivative(rng):
    """vmap(grad) under jit of the refined pose with respect to the pixels, against
    central differences of full EPnP + refinement runs."""
    pw, _, uv = _scene(rng, 2)
    noisy = jnp.asarray(uv + rng.normal(size=uv.shape) * 0.5)
    w = jnp.asarray(rng.normal(size=(2, 7)))
    k = jnp.asarray(intrinsics_matrix(520.0, 500.0, 320.0, 240.0))

    def out(p, u, v):
        return jnp.dot(epnp(p, u, k, refine_steps=20).transform.data, v)

    grads = jax.jit(jax.vmap(jax.grad(out, argnums=(0, 1))))(jnp.asarray(pw), noisy, w)
    assert all(np.all(np.isfinite(g)) for g in grads)
    f = jax.jit(jax.vmap(out))
    du = jnp.asarray(rng.normal(size=noisy.shape))
    eps = 1e-5
    fd = (f(pw, noisy + eps * du, w) - f(pw, noisy - eps * du, w)) / (2 * eps)
    np.testing.assert_allclose(jnp.sum(grads[1] * du, axis=(1, 2)), fd, rtol=1e-4, atol=1e-8)



@pytest.mark.slow  # ~60 s on the shared 2-core CI box (EPnP + LM compiled three times)
def test_second_derivative_matches_finite_differences(rng):
    """jax.hessian (fwd over rev) and jacrev(grad) (rev over rev) of a loss on the refined
    pose with respect to pixels and points against central differences of the gradient
    (the implicit rule is a differentiable function of the optimum)."""
    pw, _, uv = _scene(rng, 1)
    x0 = jnp.concatenate([jnp.asarray(pw[0]), jnp.asarray(uv[0] + rng.normal(size=(N, 2)))],
                         -1)  # (N, 5): points | noisy pixels
    k = jnp.asarray(intrinsics_matrix(520.0, 500.0, 320.0, 240.0))
    v = jnp.asarray(rng.normal(size=7))
    d = jnp.asarray(rng.normal(size=(2, N, 5)) * np.r_[0.01, 0.01, 0.01, 1.0, 1.0])

    def loss(a):
        x = x0 + jnp.tensordot(a, d, 1)
        t = epnp(x[:, :3], x[:, 3:], k, refine_steps=30).transform.data
        return jnp.dot(t, v) + jnp.sum(t ** 2 * v)

    eps, a0 = 1e-3, jnp.zeros(2)  # smaller steps meet LM stopping-tolerance jumps
    steps = jnp.concatenate([jnp.zeros((1, 2)), eps * np.eye(2), -eps * np.eye(2)])

    @jax.jit
    def run(a0):  # one compilation: FD stencil, hessian (fwd∘rev), jacrev∘grad (rev∘rev)
        vals, grads = jax.vmap(jax.value_and_grad(loss))(a0 + steps)
        return vals, grads, jax.hessian(loss)(a0), jax.jacrev(jax.grad(loss))(a0)

    vals, grads, hess, revrev = run(a0)
    fd_g = (vals[1:3] - vals[3:]) / (2 * eps)
    fd_h = (grads[1:3] - grads[3:]) / (2 * eps)
    np.testing.assert_allclose(grads[0], fd_g, rtol=1e-6, atol=1e-8 * np.abs(fd_g).max())
    for second in (hess, revrev):
        np.testing.assert_allclose(second, fd_h, rtol=1e-5, atol=1e-6 * np.abs(fd_h).max())

def test_float32(rng):
    pw, pose, uv = _scene(rng, 2)
    res = epnp(pw.astype(np.float32), uv.astype(np.float32), K.astype(np.float32),
               refine=False)
    assert res.transform.dtype == jnp.float32
    np.testing.assert_array_equal(res.status, Results.CONVERGED)
    np.testing.assert_allclose(res.transform.matrix(), pose.matrix(), atol=5e-3)


def test_bad_input():
    with pytest.raises(ValueError, match=r"epnp\(points\): EPnP needs at least 4 points, got 3"):
        epnp(np.zeros((3, 3)), np.zeros((3, 2)), K)
    with pytest.raises(ValueError, match=r"epnp\(points, pixels\).*same number"):
        epnp(np.zeros((5, 3)), np.zeros((6, 2)), K)
    with pytest.raises(ValueError, match=r"epnp\(pixels\).*\(\.\.\., N, 2\)"):
        epnp(np.zeros((5, 3)), np.zeros((5, 3)), K)
    with pytest.raises(ValueError, match=r"epnp\(intrinsics\)"):
        epnp(np.zeros((5, 3)), np.zeros((5, 2)), np.eye(4))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast"):
        epnp(np.zeros((2, 5, 3)), np.zeros((3, 5, 2)), K)


def test_transform_is_camera_extrinsics(rng):
    """The returned pose plugs into point2pixel as extrinsics (world → camera)."""
    pw, pose, uv = _scene(rng, 1)
    res = epnp_plain(pw, uv, K)
    np.testing.assert_allclose(point2pixel(pw, K, SE3(res.transform.data)), uv, atol=1e-6)


def test_non_finite_data_with_refinement_reports_status(rng):
    """NaN/inf points or pixels with refine=True (the default) used to raise the internal
    least_squares error ("residual_fn ... NaN/Inf at the initial params") instead of
    reporting NON_FINITE; other scenes of the same batch are unaffected."""
    pw, pose, uv = _scene(rng, 2)
    pw_bad = pw.copy()
    pw_bad[1, 3, 0] = np.nan
    uv_bad = uv.copy()
    uv_bad[1, 2, 1] = np.inf
    for p, u in ((pw_bad, uv), (pw, uv_bad)):
        res = epnp_refined(p, u, K)
        assert int(res.status[1]) == Results.NON_FINITE
        assert int(res.status[0]) == Results.CONVERGED
        np.testing.assert_allclose(res.transform.data[0], pose.data[0], atol=1e-8)
    eager = epnp(pw_bad[1], uv[1], K)  # eager call, default refinement
    assert int(eager.status) == Results.NON_FINITE


def test_refinement_out_of_steps_is_the_status_and_is_not_differentiated(rng):
    """One LM step does not reach the reprojection optimum of noisy data: the status says
    so (it said converged) and the implicit derivative, exact at the optimum only, raises;
    20 steps converge (test_jit_vmap_grad_implicit_derivative differentiates there)."""
    pw, _, uv = _scene(rng, 1)
    noisy = uv[0] + rng.normal(size=uv[0].shape) * 2.0

    def pose(u, steps):
        res = epnp(pw[0], u, K, refine_steps=steps)
        return res.transform.data[0], res.status

    assert int(pose(noisy, 1)[1]) == Results.MAX_STEPS
    refined = epnp_refined(pw, noisy[None], K)
    assert int(refined.status[0]) == Results.CONVERGED
    # at the optimum to the gradient's rounding level (~1e-11 here), not only where the
    # cost stops resolving decreases: LM alone stopped at 1.1e-5
    assert _tangent_gradient(pw[0], noisy, refined.transform.data[0]) < 1e-9
    with pytest.raises(Exception, match=r"epnp: cannot differentiate the solution"):
        jax.block_until_ready(jax.grad(lambda u: pose(u, 1)[0])(jnp.asarray(noisy)))


def test_a_non_finite_problem_masked_out_of_a_batch_does_not_block_its_derivative(rng):
    """A batch of two, one with a NaN pixel (NON_FINITE): the gradient of a loss that
    masks that problem out raised "epnp: cannot differentiate ... refine to convergence"
    for the whole batch (the implicit rule ran on the NaN lane under jnp.where); it now
    equals the clean problem's own gradient, and the NaN problem's is zero."""
    pw, _, uv = _scene(rng, 2)
    noisy = uv + rng.normal(size=uv.shape) * 0.5
    bad = noisy.copy()
    bad[1, 0, 0] = np.nan
    w = jnp.asarray(rng.normal(size=7))

    def loss(u):
        res = epnp(pw, u, K, refine_steps=20)
        return jnp.sum(jnp.where(res.status[:, None] == Results.CONVERGED,
                                 res.transform.data * w, 0.0))

    g = jax.jit(jax.grad(loss))(jnp.asarray(bad))
    single = jax.jit(jax.grad(
        lambda u: jnp.sum(epnp(pw[0], u, K, refine_steps=20).transform.data * w)))(
            jnp.asarray(noisy[0]))
    np.testing.assert_allclose(g[0], single, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(g[1], 0.0)
