"""ICP recovers known transforms; statuses; implicit derivatives vs finite differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose import Results
from jaxpose.geometry import estimate_normals, icp
from jaxpose.lie import SE3

from .conftest import random_rotation, se3_from_rt


def _cloud(rng: np.random.Generator, n: int) -> np.ndarray:
    """A non-symmetric synthetic scan: three unequal planes and a blob."""
    u = rng.uniform(-1, 1, size=(n, 2))
    k = n // 4
    parts = [
        np.c_[u[:k, 0] * 2.0, u[:k, 1], np.zeros(k)],
        np.c_[np.zeros(k), u[k:2 * k, 0] * 1.5, u[k:2 * k, 1] * 0.8 + 0.8],
        np.c_[u[2 * k:3 * k, 0], np.full(k, -1.0), u[2 * k:3 * k, 1] * 0.5 + 0.5],
        rng.normal(size=(n - 3 * k, 3)) * 0.2 + np.array([1.0, 0.5, 0.6]),
    ]
    return np.concatenate(parts)


def _small_motion(rng, angle=0.15, shift=0.1):
    axis = rng.normal(size=3)
    phi = axis / np.linalg.norm(axis) * angle
    return SE3.exp(jnp.asarray(np.r_[rng.normal(size=3) * shift, phi]))


icp_p2p = jax.jit(lambda s, t, i: icp(s, t, SE3(i), max_iterations=60, tolerance=1e-10))


def test_point_to_point_recovers_transform_batched(rng):
    src = np.stack([_cloud(rng, 400), _cloud(rng, 400)])
    truth = SE3(jnp.stack([_small_motion(rng).data, _small_motion(rng).data]))
    tgt = np.asarray(truth[:, None].act(src))
    tgt = tgt[:, rng.permutation(400)]  # correspondences unknown
    res = icp_p2p(src, tgt, SE3.identity((2,)).data)
    np.testing.assert_array_equal(res.status, Results.CONVERGED)
    np.testing.assert_allclose(res.transform.matrix(), truth.matrix(), atol=1e-9)
    np.testing.assert_allclose(res.rmse, 0.0, atol=1e-9)
    np.testing.assert_allclose(res.fitness, 1.0)
    assert np.all(res.iterations > 1)


def test_point_to_plane_and_kdtree(rng):
    src = _cloud(rng, 600)
    truth = _small_motion(rng, 0.1, 0.05)
    tgt = np.asarray(truth.act(src))
    nrm = estimate_normals(tgt, k=8, method="kdtree")
    res = icp(src, tgt, method="point_to_plane", target_normals=nrm, knn_method="kdtree",
              max_iterations=40, tolerance=1e-12)
    assert int(res.status) == Results.CONVERGED
    np.testing.assert_allclose(res.transform.matrix(), truth.matrix(), atol=1e-8)


def test_estimate_normals_plane_and_sphere(rng):
    n = np.array([1.0, 2.0, 2.0]) / 3.0
    basis = np.linalg.svd(n[None])[2][1:]  # two in-plane directions
    plane = rng.uniform(-1, 1, size=(300, 2)) @ basis + 0.5
    got = np.asarray(estimate_normals(plane, k=10))
    np.testing.assert_allclose(np.abs(got @ n), 1.0, atol=1e-12)
    sphere = rng.normal(size=(400, 3))
    sphere /= np.linalg.norm(sphere, axis=-1, keepdims=True)
    out = np.asarray(estimate_normals(sphere, k=6, viewpoint=np.zeros(3)))
    cos = np.sum(out * sphere, -1)  # radial (up to curvature), facing the centre
    assert np.all(cos < -0.85) and np.mean(cos) < -0.98


def _central(f, x, h=1e-6):
    """Central differences of f at x (…) → (*f.shape, *x.shape)."""
    cols = []
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = h
        e = e.reshape(x.shape)
        cols.append((np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * h))
    return np.stack(cols, -1).reshape(*np.shape(f(x)), *x.shape)


def test_estimate_normals_derivatives_on_a_grid_and_a_noisy_patch(rng):
    """A regular grid's neighbourhoods have two equal in-plane eigenvalues: eigh's
    derivative (1/(λᵢ − λⱼ) for every pair) made reverse mode NaN there (153 of the centre
    normal's 225 entries). The normal's own derivative needs only its eigenvalue simple:
    jacrev = jacfwd = central differences, on the grid and on a noisy patch, and second
    derivatives too; collinear neighbours (the normal is not unique) stay finite."""
    g = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0), indexing="ij"), -1)
    grid = np.c_[g.reshape(-1, 2), np.zeros(25)]
    noisy = grid + rng.normal(scale=0.05, size=grid.shape)
    vp = np.array([0.3, 0.2, 10.0])
    for pts in (grid, noisy):
        f = jax.jit(lambda p: estimate_normals(p, k=9, viewpoint=vp)[12])  # the centre's
        fd = _central(f, pts)
        for jac in (jax.jacrev(f)(pts), jax.jacfwd(f)(pts)):
            np.testing.assert_allclose(jac, fd, atol=1e-8)
    loss = jax.jit(lambda p: jnp.sum(estimate_normals(p, k=9, viewpoint=vp)[:, 2] ** 3))
    hess = jax.hessian(loss)(noisy)[12, 2]  # row of one coordinate, against FD of grad
    np.testing.assert_allclose(hess, _central(jax.grad(loss), noisy)[..., 12, 2], atol=1e-6)
    line = np.c_[np.arange(6.0), np.zeros(6), np.zeros(6)]
    assert np.all(np.isfinite(jax.jacrev(lambda p: estimate_normals(p, k=3))(line)))
    # float32 on a strip 1 % as wide as long (in-plane gap/trace ~ 1e-4): a well-defined
    # normal whose derivative a too wide "not simple" threshold had set to 0 (review)
    x, y = np.meshgrid(np.arange(15.0), np.array([-0.01, 0.0, 0.01]), indexing="ij")
    strip = np.c_[x.ravel(), y.ravel(), 1e-4 * rng.normal(size=x.size)]
    g = lambda p: estimate_normals(p, k=9, viewpoint=vp.astype(p.dtype))[22]  # noqa: E731
    fd = _central(jax.jit(g), strip, h=1e-7)
    jac32 = np.asarray(jax.jacfwd(g)(jnp.asarray(strip, jnp.float32)))
    np.testing.assert_allclose(jac32, fd, atol=1e-5 * np.abs(fd).max())
    huge = jnp.asarray(strip * 1e20, jnp.float32)  # its covariance overflows: NaN normals
    assert np.all(np.isnan(g(huge))) and np.all(np.isnan(jax.jacfwd(g)(huge)))  # not 0


@pytest.mark.parametrize("method", ["point_to_point", "point_to_plane"])
def test_derivative_with_respect_to_init_is_zero_in_both_modes(rng, method):
    """The documented zero: forward mode gave it, reverse mode raised JAX's while_loop
    error, also for a parameter that only computes init (a network's coarse pose)."""
    src = _cloud(rng, 200)
    tgt = np.asarray(_small_motion(rng, 0.05, 0.02).act(src))
    kw = {"method": method, "max_iterations": 30}
    if method == "point_to_plane":
        kw["target_normals"] = estimate_normals(tgt, k=8)

    def translation(xi):
        return icp(src, tgt, init=SE3.exp(xi), **kw).transform.translation()

    xi = jnp.asarray(rng.normal(size=6) * 0.01)
    for jac in (jax.jacrev(translation)(xi), jax.jacfwd(translation)(xi)):
        np.testing.assert_array_equal(jac, 0.0)
    grad = jax.grad(lambda s: jnp.sum(icp(s, tgt, init=SE3.exp(xi), **kw).transform.data))
    assert np.all(np.isfinite(grad(src)))  # the other derivatives are unaffected


def test_outlier_gate_and_statuses(rng):
    src = _cloud(rng, 200)
    truth = _small_motion(rng, 0.05, 0.02)
    tgt = np.asarray(truth.act(src))
    # 20 source points with no counterpart, far away: the gate must ignore them
    src_out = np.concatenate([src, rng.normal(size=(20, 3)) + 30.0])
    f = jax.jit(lambda s, t, it, md: icp(s, t, max_iterations=it, max_distance=md,
                                         tolerance=1e-10))
    gated = f(src_out, tgt, 60, 0.5)
    assert int(gated.status) == Results.CONVERGED
    assert float(gated.fitness) == pytest.approx(200 / 220)
    np.testing.assert_allclose(gated.transform.matrix(), truth.matrix(), atol=1e-9)
    ungated = f(src_out, tgt, 60, np.inf)
    assert float(ungated.fitness) == 1.0
    assert np.max(np.abs(ungated.transform.matrix() - truth.matrix())) > 1e-3
    src_out = src_out[:200]
    assert int(f(src_out, tgt, 1, np.inf).status) == Results.MAX_STEPS
    degenerate = f(src_out, tgt + 100.0, 60, 0.5)  # nothing within the gate
    assert int(degenerate.status) == Results.DEGENERATE
    np.testing.assert_allclose(degenerate.transform.matrix(), np.eye(4))
    bad = f(src_out, np.where(np.arange(200)[:, None] == 3, np.nan, tgt), 60, np.inf)
    assert int(bad.status) == Results.NON_FINITE
    assert np.all(np.isfinite(np.asarray(bad.transform.data)))


def test_implicit_derivative_matches_finite_differences(rng):
    """d T / d source through the loop: vmap(grad) under jit against central differences
    of full ICP runs (small perturbations keep the converged correspondences)."""
    src = jnp.asarray(_cloud(rng, 120))
    truth = _small_motion(rng, 0.08, 0.05)
    tgt = truth.act(src) + jnp.asarray(rng.normal(size=(120, 3)) * 0.01)  # noisy: LS fit
    w = jnp.asarray(rng.normal(size=(2, 7)))

    def out(s, v):
        return jnp.dot(icp(s, tgt, max_iterations=50, tolerance=1e-12).transform.data, v)

    grads = jax.jit(jax.vmap(jax.grad(out), in_axes=(None, 0)))(src, w)
    assert np.all(np.isfinite(grads))
    f = jax.jit(out)
    direction = jnp.asarray(rng.normal(size=src.shape))
    eps = 1e-6
    for i in range(2):
        fd = (f(src + eps * direction, w[i]) - f(src - eps * direction, w[i])) / (2 * eps)
        np.testing.assert_allclose(jnp.sum(grads[i] * direction), fd, rtol=1e-5, atol=1e-8)



def _second_derivative_errors(loss, x0, directions, eps):
    """Max relative errors of the gradient of a ↦ loss(x0 + a·D) against central
    differences of the value, and of jax.hessian (fwd over rev) and jacrev(grad) (rev over
    rev) against central differences of that gradient (one compilation)."""
    f = lambda a: loss(x0 + jnp.tensordot(a, directions, 1))
    m = directions.shape[0]
    a0 = jnp.zeros(m, x0.dtype)
    steps = jnp.concatenate([jnp.zeros((1, m)), eps * np.eye(m), -eps * np.eye(m)])

    @jax.jit
    def run(a0):
        vals, grads = jax.vmap(jax.value_and_grad(f))(a0 + steps)
        return vals, grads, jax.hessian(f)(a0), jax.jacrev(jax.grad(f))(a0)

    vals, grads, hess, revrev = run(a0)
    fd_g = (vals[1:m + 1] - vals[m + 1:]) / (2 * eps)
    fd_h = (grads[1:m + 1] - grads[m + 1:]) / (2 * eps)
    rel = lambda x, ref: float(np.max(np.abs(x - ref)) / np.max(np.abs(ref)))
    return rel(grads[0], fd_g), rel(hess, fd_h), rel(revrev, fd_h)


@pytest.mark.parametrize("method", [
    pytest.param("point_to_point", marks=pytest.mark.slow),  # Kabsch: see test_registration
    "point_to_plane",
])
def test_second_derivative_matches_finite_differences(rng, method):
    """Second derivatives of a loss on the ICP pose with respect to the source and target
    points (both implicit rules are differentiable functions of the optimum) against
    central differences of the first derivative."""
    src = jnp.asarray(_cloud(rng, 40))
    tgt = _small_motion(rng, 0.08, 0.05).act(src) + jnp.asarray(rng.normal(size=(40, 3)) * 0.01)
    kw = {}
    if method == "point_to_plane":
        kw["target_normals"] = estimate_normals(tgt, k=8)
    v = jnp.asarray(rng.normal(size=7))
    d = jnp.asarray(rng.normal(size=(2, 2, 40, 3)))

    def loss(x):  # x stacks source and target: (2, 40, 3)
        t = icp(x[0], x[1], method=method, max_iterations=50, tolerance=1e-13, **kw)
        return jnp.dot(t.transform.data, v) + jnp.sum(t.transform.data ** 2 * v)

    errs = _second_derivative_errors(loss, jnp.stack([src, tgt]), d, 1e-5)
    assert max(errs) < 1e-5, errs

def test_bad_input(rng):
    z = np.zeros((10, 3))
    with pytest.raises(ValueError, match=r"icp\(source\).*empty"):
        icp(np.zeros((0, 3)), z)
    with pytest.raises(ValueError, match=r"icp\(target_normals\).*point_to_plane"):
        icp(z, z, method="point_to_plane")
    with pytest.raises(ValueError, match=r"icp\(method\)"):
        icp(z, z, method="plane")
    with pytest.raises(TypeError, match=r"icp\(init\).*SE3"):
        icp(z, z, init=np.zeros(7))
    with pytest.raises(ValueError, match=r"icp\(max_distance\)"):
        icp(z, z, max_distance=-1.0)
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast"):
        icp(np.zeros((2, 10, 3)), np.zeros((3, 10, 3)))


@pytest.mark.slow
def test_larger_cloud_kdtree_float32(rng):
    src = _cloud(rng, 20_000).astype(np.float32)
    truth = se3_from_rt(random_rotation(rng) @ np.eye(3), np.zeros(3))
    truth = _small_motion(rng, 0.1, 0.1)
    tgt = np.asarray(truth.act(src), np.float32)[rng.permutation(20_000)]
    res = icp(src, tgt, knn_method="kdtree", max_iterations=80)
    assert int(res.status) == Results.CONVERGED
    np.testing.assert_allclose(res.transform.matrix(), truth.matrix(), atol=1e-4)


def test_huge_coordinates_give_finite_rmse_or_non_finite_status(rng):
    """Coordinates of 1e200: the squared distances overflow; the RMSE used to be inf with
    status SUCCESS. It is now formed scale-safely (finite, of the size of the offsets)."""
    src = _cloud(rng, 40)
    res = icp(src * 1e200, src * 1e200 + 1e199, max_iterations=3)
    assert np.isfinite(float(res.rmse)) or int(res.status) == Results.NON_FINITE
    if int(res.status) == Results.CONVERGED:
        assert 1e198 < float(res.rmse) < 1e201
    # degenerate geometry (documented as DEGENERATE): collinear or coincident source points
    # leave the rotation about the line undetermined; this used to report SUCCESS
    line = np.outer(np.linspace(-1.0, 1.0, 40), [1.0, 0.5, 0.2])
    for pts in (line, np.ones((40, 3))):
        res = icp(pts, pts + np.array([0.1, 0.0, 0.0]), max_iterations=3)
        assert int(res.status) == Results.DEGENERATE


def test_point_to_plane_derivative_of_an_unconverged_loop_raises(rng):
    """Two iterations leave point-to-plane ICP short of its fixed point (status
    max_steps): its implicit derivative there would be wrong, so differentiating raises;
    with enough iterations it differentiates."""
    src = _cloud(rng, 200)
    tgt = np.asarray(_small_motion(rng, 0.1, 0.05).act(src))
    nrm = np.asarray(estimate_normals(tgt, k=8))

    def shift(s, iterations):
        res = icp(s, tgt, method="point_to_plane", target_normals=nrm,
                  max_iterations=iterations, tolerance=1e-12)
        return res.transform.data[0], res.status

    assert int(shift(src, 2)[1]) == Results.MAX_STEPS
    with pytest.raises(Exception, match=r"icp\(method='point_to_plane'\): cannot differentiate"):
        jax.block_until_ready(jax.grad(lambda s: shift(s, 2)[0])(jnp.asarray(src)))
    assert np.all(np.isfinite(jax.grad(lambda s: shift(s, 40)[0])(jnp.asarray(src))))


@pytest.mark.parametrize("method", ["point_to_point", "point_to_plane"])
def test_a_nan_problem_masked_out_of_a_batch_leaves_the_others_gradient(rng, method):
    """A NON_FINITE problem (a NaN source point) returns its start, whose derivative is
    zero, but its discarded re-solve was still differentiated: point to point on the NaN
    data (0·NaN made the gradient of a loss that masks it out NaN for the whole batch, a
    shared shift), point to plane with its NON_FINITE status (it raised "cannot
    differentiate" for the whole batch)."""
    tgt = jnp.asarray(rng.normal(size=(200, 3)))
    src = SE3.exp(jnp.array([0.02, -0.01, 0.01, 0.02, 0.0, -0.03])).inv().act(tgt[:150])
    batch = jnp.stack([src, src.at[3, 1].set(jnp.nan)])
    nrm = estimate_normals(tgt, k=8) if method == "point_to_plane" else None

    def loss(shift, clouds):
        r = icp(clouds + shift, tgt, method=method, target_normals=nrm, tolerance=1e-12,
                max_iterations=100)
        per = jnp.sum(r.transform.data, -1)
        return jnp.sum(jnp.where(r.status == Results.CONVERGED, per, 0.0))

    grad = jax.jit(jax.grad(loss))
    status = icp(batch, tgt, method=method, target_normals=nrm, tolerance=1e-12,
                 max_iterations=100).status
    assert status.tolist() == [0, 3]
    # with the k-d tree too: vmapped, the loop body ran for the stopped NaN problem and
    # the tree's NaN check raised for the whole batch (vmap audit)
    kd = icp(batch, tgt, method=method, target_normals=nrm, knn_method="kdtree")
    assert kd.status.tolist() == [0, 3]
    alone = grad(jnp.zeros(3), src[None])
    assert np.all(np.isfinite(alone)) and np.abs(alone).max() > 0.1
    np.testing.assert_allclose(grad(jnp.zeros(3), batch), alone, rtol=1e-12)


def test_an_unconverged_point_to_plane_problem_masked_out_of_a_batch(rng):
    """Five iterations: the small motion converges, the large one stops (max_steps). A
    loss that masks the second out has the first's own gradient; it raised "cannot
    differentiate" for the whole batch. Unmasked, it still raises."""
    tgt = jnp.asarray(rng.normal(size=(200, 3)))
    nrm = estimate_normals(tgt, k=8)
    motions = jnp.array([[0.02, -0.01, 0.01, 0.02, 0.0, -0.03],
                         [0.3, -0.2, 0.1, 0.2, 0.1, -0.3]])
    batch = jax.vmap(lambda m: SE3.exp(m).inv().act(tgt[:150]))(motions)

    def per_problem(shift, clouds):
        r = icp(clouds + shift, tgt, method="point_to_plane", target_normals=nrm,
                tolerance=1e-12, max_iterations=5)
        return jnp.sum(r.transform.data, -1), r.status

    def masked(shift, clouds):
        values, status = per_problem(shift, clouds)
        return jnp.sum(jnp.where(status == Results.CONVERGED, values, 0.0))

    assert per_problem(jnp.zeros(3), batch)[1].tolist() == [0, 1]
    grad = jax.jit(jax.grad(masked))
    alone = grad(jnp.zeros(3), batch[:1])
    assert np.abs(alone).max() > 0.1
    np.testing.assert_allclose(grad(jnp.zeros(3), batch), alone, rtol=1e-12)
    with pytest.raises(Exception, match=r"icp\(method='point_to_plane'\): cannot differentiate"):
        jax.block_until_ready(jax.grad(lambda s: per_problem(s, batch)[0].sum())(jnp.zeros(3)))
