"""Bundle adjustment: the BAL reprojection factor, Schur elimination vs the full system,
convergence to the noise floor on a synthetic problem and to SciPy's minimum on the BAL
files.

References independent of the code under test: the camera model in numpy with SciPy's
rotation (``_project``), a dense numpy solve of the damped normal equations assembled from
``jax.jacfwd`` of the whole graph's residual (``conftest.dense_residual_fn``), and
``scipy.optimize.least_squares`` on BAL's own parametrisation (Rodrigues vectors).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from jaxpose.datasets import synthetic_bal
from jaxpose.graph import (
    Factor,
    FactorGraph,
    default_stopping,
    prior_residual,
    solve,
    vector_prior_residual,
)
from jaxpose.graph import _ba as bal_graph
from jaxpose.graph import _linear as linear
from jaxpose.graph._problem import gradient, hessian_diagonal, jtj_blocks, linearize
from jaxpose.graph._schur import schur_parts, schur_step
from jaxpose.io import BALProblem, read_bal
from jaxpose.lie import SE3
from jaxpose.optim import Nielsen

from .conftest import DATA, FAST_COMPILE, assemble_jacobian, dense_residual_fn, jit_solve

BA_OPTIONS = dict(damping="diagonal", strategy=Nielsen(1e-4), stopping=default_stopping(60))


def _project(cameras: np.ndarray, points: np.ndarray, cam: np.ndarray, pt: np.ndarray):
    c = cameras[cam]
    P = Rotation.from_rotvec(c[:, :3]).apply(points[pt]) + c[:, 3:6]
    p = -P[:, :2] / P[:, 2:]
    r2 = np.sum(p * p, 1, keepdims=True)
    return c[:, 6:7] * (1 + c[:, 7:8] * r2 + c[:, 8:9] * r2 * r2) * p


def _bal_file(name: str) -> BALProblem:
    path = DATA / "bal" / name
    if not path.is_file():
        pytest.skip(f"reference data {path} not present")
    return read_bal(path)


def _small_problem(seed: int = 0):
    return synthetic_bal(n_cameras=6, n_points=40, obs_per_point=3, seed=seed)


def test_reprojection_factor_model_and_jacobians():
    """Residuals equal the numpy camera model; analytic Jacobian blocks equal jacfwd through
    the retraction (pose: right perturbation) at random cameras, in float64 and float32."""
    prob, _ = _small_problem(1)
    graph = bal_graph.bundle_adjustment_problem(prob)
    auto = FactorGraph([Factor(bal_graph.reprojection_residual, [
        ("pose", prob.camera_index), ("intrinsics", prob.camera_index),
        ("point", prob.point_index)], data=graph.factors[0].data)], graph.variables)

    @jax.jit(compiler_options=FAST_COMPILE)
    def run(graph, auto):
        return linearize(graph, graph.variables), linearize(auto, auto.variables)

    analytic, ref = run(graph, auto)
    want = _project(prob.cameras, prob.points, prob.camera_index, prob.point_index)
    np.testing.assert_allclose(analytic.residuals[0], want - prob.observations, rtol=0,
                               atol=1e-9 * np.abs(want).max())
    for got, exp, name in zip(analytic.jacobians[0], ref.jacobians[0],
                              ("pose", "intrinsics", "point"), strict=True):
        exp = np.asarray(exp)
        np.testing.assert_allclose(got, exp, rtol=0, atol=1e-10 * np.abs(exp).max(),
                                   err_msg=name)
    np.testing.assert_allclose(float(analytic.cost),
                               0.5 * np.sum((want - prob.observations) ** 2), rtol=1e-12)
    # round trip of the BAL camera parametrisation
    cams, pts = bal_graph.variables_to_bal(graph.variables)
    np.testing.assert_allclose(cams, prob.cameras, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(pts, prob.points)
    # float32: same model to float32 precision
    g32 = bal_graph.bundle_adjustment_problem(prob, dtype=jnp.float32)
    lin32, _ = run(g32, auto)
    assert lin32.residuals[0].dtype == jnp.float32
    np.testing.assert_allclose(lin32.residuals[0], want - prob.observations, rtol=0,
                               atol=1e-4 * np.abs(want).max())


def _schur_graph():
    """A small BA graph plus factors that touch only kept variables (a pose prior) or only
    an eliminated one (a point prior), with fixed variables of every type."""
    prob, _ = _small_problem(2)
    base = bal_graph.bundle_adjustment_problem(prob)
    rng = np.random.default_rng(3)
    prior_pose = SE3(base.variables["pose"].data[:2]).retract(
        jnp.asarray(0.01 * rng.normal(size=(2, 6))))
    factors = [
        base.factors[0],
        Factor(prior_residual, [("pose", np.array([1, 3]))], data=prior_pose,
               information=np.diag([4.0, 4, 4, 100, 100, 100])),
        Factor(vector_prior_residual, [("point", np.array([0, 5]))],
               data=jnp.asarray(prob.points[[0, 5]] + 0.1), information=np.eye(3) * 2.0),
    ]
    fixed = {"pose": [0], "intrinsics": [0, 2], "point": [7]}
    graph = FactorGraph(factors, base.variables, fixed=fixed, eliminate="point")
    info = [None, np.diag([4.0, 4, 4, 100, 100, 100]), np.eye(3) * 2.0]
    return graph, info


def test_schur_step_equals_the_dense_solve_of_the_full_system():
    graph, info = _schur_graph()
    st = graph.structure
    assert st.schur is not None and st.names == ("intrinsics", "point", "pose")

    @jax.jit(compiler_options=FAST_COMPILE)
    def run(graph):
        lin = linearize(graph, graph.variables)
        g = gradient(graph, lin)
        free = jnp.concatenate([jnp.repeat(f, d) for f, d in zip(st.free, st.dims,
                                                                  strict=True)])
        add = 1e-3 * jnp.clip(hessian_diagonal(graph, lin), 1e-6, 1e32) + (1.0 - free)
        ref = dense_residual_fn(graph, graph.variables, info)
        zero = jnp.zeros(graph.size)
        return dict(
            lin=lin, g=g, add=add, free=free, J_ref=jax.jacfwd(ref)(zero), r_ref=ref(zero),
            dense=schur_step(graph, schur_parts(graph, jtj_blocks(lin, g.dtype), g.dtype), g, add,
                             linear.solve_dense),
            sparse=schur_step(graph, schur_parts(graph, jtj_blocks(lin, g.dtype), g.dtype), g, add,
                              linear.solve_sparse_direct),
        )

    out = run(graph)
    free = np.asarray(out["free"])
    J = np.asarray(out["J_ref"]) * free[None, :]
    np.testing.assert_allclose(assemble_jacobian(graph, out["lin"].jacobians), J, rtol=0,
                               atol=1e-9 * np.abs(J).max())
    H = J.T @ J
    np.testing.assert_allclose(out["add"], 1e-3 * np.clip(np.diag(H), 1e-6, 1e32) + 1 - free,
                               rtol=1e-9, atol=0)
    x = np.linalg.solve(H + np.diag(np.asarray(out["add"])), -(J.T @ np.asarray(out["r_ref"])))
    for key in ("dense", "sparse"):
        np.testing.assert_allclose(out[key], x, rtol=0, atol=1e-9 * np.abs(x).max(), err_msg=key)
        assert np.all(np.asarray(out[key])[free == 0] == 0), key


def test_schur_and_plain_solves_agree_and_reach_the_noise_floor():
    """LM with Schur elimination and with the full sparse system take the same steps; the
    result fits the data as well as the truth does and its RMSE is the noise floor
    σ·√((M − P + 7)/M) (M residuals, P parameters, 7 gauge freedoms)."""
    prob, truth = synthetic_bal(n_cameras=8, n_points=120, obs_per_point=4, seed=5)
    sols = {}
    for solver in ("schur", "sparse"):
        graph = bal_graph.bundle_adjustment_problem(prob, eliminate=solver == "schur")
        sols[solver] = jit_solve(linear_solver=solver, **BA_OPTIONS)(graph)
    a, b = sols["schur"], sols["sparse"]
    assert a.status_name == b.status_name == "converged"
    assert int(a.iterations) == int(b.iterations)
    np.testing.assert_allclose(float(a.cost), float(b.cost), rtol=1e-10)
    np.testing.assert_allclose(a.variables["point"], b.variables["point"], rtol=0, atol=1e-7)
    rmse = bal_graph.reprojection_rmse(prob, a.variables)
    m = 2 * prob.n_observations
    n_params = 9 * prob.n_cameras + 3 * prob.n_points
    floor = np.sqrt((m - n_params + 7) / m)  # σ = 1 pixel
    assert abs(rmse / floor - 1) < 0.15, (rmse, floor)
    assert float(a.cost) < 0.5 * m * bal_graph.reprojection_rmse(truth) ** 2
    assert bal_graph.reprojection_rmse(prob) > 10 * rmse  # it really moved


def _scipy_minimum(prob: BALProblem) -> float:
    """Minimum of 0.5·Σ‖r‖² over poses and points (intrinsics fixed), BAL parametrisation."""
    nc = prob.n_cameras

    def res(x):
        cams = prob.cameras.copy()
        cams[:, :6] = x[: 6 * nc].reshape(nc, 6)
        pts = x[6 * nc :].reshape(-1, 3)
        return (_project(cams, pts, prob.camera_index, prob.point_index)
                - prob.observations).ravel()

    x0 = np.concatenate([prob.cameras[:, :6].ravel(), prob.points.ravel()])
    r = least_squares(res, x0, method="trf", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return 0.5 * float(np.sum(r.fun**2))


def test_bal_file_fixed_intrinsics_reaches_scipy_minimum():
    prob = _bal_file("dubrovnik-3-7-pre.txt")
    graph = bal_graph.bundle_adjustment_problem(prob, fix_intrinsics=True)
    sol = jit_solve(linear_solver="schur", **BA_OPTIONS)(graph)
    assert sol.status_name == "converged"
    cams, pts = bal_graph.variables_to_bal(sol.variables)
    out = BALProblem(cams, pts, prob.camera_index, prob.point_index, prob.observations)
    np.testing.assert_allclose(float(sol.cost), _scipy_minimum(prob), rtol=1e-8)
    np.testing.assert_array_equal(out.cameras[:, 6:], prob.cameras[:, 6:])
    rmse = bal_graph.reprojection_rmse(out)
    np.testing.assert_allclose(0.5 * 2 * prob.n_observations * rmse**2, float(sol.cost),
                               rtol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["dubrovnik-1-1-pre.txt", "dubrovnik-3-7-18-pre.txt",
                                  "dubrovnik-3-7-pre.txt"])
def test_bal_files_converge(name):
    """All nine camera parameters free: the small files have fewer residuals than
    parameters, so the noise floor is zero; with intrinsics fixed, SciPy's minimum."""
    prob = _bal_file(name)
    out, sol = bal_graph.optimize_bal(prob, stopping=default_stopping(300))
    assert sol.status_name == "converged"
    assert bal_graph.reprojection_rmse(out) < 1e-9 < bal_graph.reprojection_rmse(prob)
    _, fixed = bal_graph.optimize_bal(prob, fix_intrinsics=True,
                                    stopping=default_stopping(100))
    np.testing.assert_allclose(float(fixed.cost), _scipy_minimum(prob), rtol=1e-8, atol=1e-20)


@pytest.mark.slow
def test_float32_schur_solve():
    prob, _ = synthetic_bal(n_cameras=8, n_points=120, obs_per_point=4, seed=5)
    g64 = bal_graph.bundle_adjustment_problem(prob)
    g32 = bal_graph.bundle_adjustment_problem(prob, dtype=jnp.float32)
    s64 = jit_solve(linear_solver="schur", **BA_OPTIONS)(g64)
    opts32 = {**BA_OPTIONS, "stopping": default_stopping(60, jnp.float32)}
    s32 = jax.jit(lambda g: bal_graph.solve(g, linear_solver="schur", **opts32),
                  compiler_options=FAST_COMPILE)(g32)
    assert s32.cost.dtype == jnp.float32 and s32.status_name in ("converged", "diverged")
    np.testing.assert_allclose(float(s32.cost), float(s64.cost), rtol=1e-4)


def test_bad_bundle_adjustment_input():
    prob, _ = _small_problem(0)
    with pytest.raises(TypeError, match=r"expected a BALProblem"):
        bal_graph.bundle_adjustment_problem(prob.cameras)
    with pytest.raises(ValueError, match=r"bal_to_variables\(cameras\).*\(n, 9\)"):
        bal_graph.bal_to_variables(prob.cameras[:, :7], prob.points)
    empty = BALProblem(prob.cameras, prob.points, np.zeros(0, np.int64), np.zeros(0, np.int64),
                       np.zeros((0, 2)))
    with pytest.raises(ValueError, match="no observations"):
        bal_graph.bundle_adjustment_problem(empty)
    graph = bal_graph.bundle_adjustment_problem(prob, eliminate=False)
    with pytest.raises(ValueError, match="eliminates no variable type"):
        bal_graph.solve(graph, linear_solver="schur")
    with pytest.raises(KeyError, match=r"eliminate='landmark'.*not a variable type"):
        FactorGraph(graph.factors, graph.variables, eliminate="landmark")
    link = Factor(lambda a, b, z: a - b, [("point", np.array([0])), ("point", np.array([1]))],
                  data=jnp.zeros((1, 3)))
    with pytest.raises(ValueError, match="links two 'point' variables"):
        FactorGraph([graph.factors[0], link], graph.variables, eliminate="point")


def _ba_loss(linear_solver: str, theta):
    """Σ w·points + cost of the solved Schur test graph with observations + θ."""
    import equinox as eqx

    graph, _ = _schur_graph()
    graph = eqx.tree_at(lambda g: g.factors[0].data, graph, graph.factors[0].data + theta)
    sol = solve(graph, linear_solver=linear_solver, **BA_OPTIONS)
    w = jnp.asarray(np.random.default_rng(4).normal(size=sol.variables["point"].shape))
    return jnp.sum(w * sol.variables["point"]) + sol.cost


@jax.jit(compiler_options=FAST_COMPILE)
def _dense_cost_hessian(graph):
    """``jax.hessian`` of the graph's cost in its tangent chart at its variables."""
    from jaxpose.graph._problem import cost, retract_all

    return jax.hessian(lambda d: cost(graph, retract_all(graph, graph.variables, d,
                                                         "retract_quadratic")))(
        jnp.zeros(graph.structure.size))


@pytest.mark.parametrize("chunk", [7, 1000])
def test_exact_schur_parts_in_chunks_give_the_dense_schur_complement(monkeypatch, chunk):
    """The backward's Schur pieces of the exact Hessian, assembled HESSIAN_CHUNK factors
    at a time (120 reprojections: 17 chunks of 7 and an overlapping last one; or one
    chunk), reduce to the Schur complement of the dense ``jax.hessian`` of the cost
    (fixed variables: identity rows), and their eliminated blocks to its point block."""
    import scipy.sparse as sp

    from jaxpose.graph import _implicit
    from jaxpose.graph._problem import free_flat
    from jaxpose.graph._schur import reduced_system

    monkeypatch.setattr(_implicit, "HESSIAN_CHUNK", chunk)
    graph, _ = _schur_graph()
    st, sc = graph.structure, graph.structure.schur
    xs = graph.variables
    add = 1.0 - free_flat(graph, jnp.float64)

    # a fresh function: jit's cache does not see the patched chunk size
    @jax.jit(compiler_options=FAST_COMPILE)
    def reduced(graph, xs):
        data, v_inv, _, _ = reduced_system(graph, _implicit._exact_schur_parts(graph, xs), add)
        return data, v_inv

    data, v_inv = reduced(graph, xs)
    got = sp.csr_matrix((np.asarray(data), sc.pattern.indices, sc.pattern.indptr)).toarray()
    h = np.array(_dense_cost_hessian(graph)) + np.diag(np.asarray(add))
    spans = [np.arange(o, o + n * d) for o, n, d in
             zip(st.offsets[:-1], st.counts, st.dims, strict=True)]
    e = spans[sc.eliminated]
    k = np.concatenate([spans[t] for t in sc.kept])
    want = h[np.ix_(k, k)] - h[np.ix_(k, e)] @ np.linalg.solve(h[np.ix_(e, e)], h[np.ix_(e, k)])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10 * np.abs(want).max())
    v = np.linalg.inv(np.asarray(v_inv))
    d = st.dims[sc.eliminated]
    np.testing.assert_allclose(
        v, [h[np.ix_(e[d * i:d * i + d], e[d * i:d * i + d])] for i in range(v.shape[0])],
        rtol=0, atol=1e-9 * np.abs(h).max())


# slow tier: compiles two BA gradients (~20 s; the default run is over its ~6 min budget)
@pytest.mark.slow
@pytest.mark.parametrize("order", ["grad", "hessian"])
def test_schur_backward_equals_the_sparse_backward(order):
    """The implicit rule's solve by Schur elimination of the exact Hessian (the forward's
    ``linear_solver="schur"``) gives the derivatives of the full sparse solve, at first
    and second order, with fixed variables of every type."""
    graph, _ = _schur_graph()
    theta = jnp.zeros_like(graph.factors[0].data)
    d = jax.grad if order == "grad" else (lambda f: jax.jacfwd(jax.grad(f)))
    got = jax.jit(d(partial(_ba_loss, "schur")), compiler_options=FAST_COMPILE)(theta)
    want = jax.jit(d(partial(_ba_loss, "sparse")), compiler_options=FAST_COMPILE)(theta)
    assert np.all(np.isfinite(np.asarray(got))) and float(jnp.max(jnp.abs(want))) > 1e-3
    np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-9 * float(jnp.max(jnp.abs(want))))


def test_float32_ba_gradient_through_the_schur_backward():
    """A float32 BA graph (two cameras held at their true values): the gradient through
    the Schur-eliminated solve and its Schur-eliminated backward is float32 and equals the
    float64 gradient to float32 accuracy (3e-5 relative here)."""
    import dataclasses

    import equinox as eqx

    prob, truth = _small_problem(4)
    cameras = np.array(prob.cameras)
    cameras[:2] = truth.cameras[:2]
    prob = dataclasses.replace(prob, cameras=cameras)
    w = np.random.default_rng(5).normal(size=(prob.points.shape[0], 3))

    def ba_gradient(dtype):
        graph = bal_graph.bundle_adjustment_problem(prob, dtype=dtype, fixed_cameras=[0, 1])
        opts = {**BA_OPTIONS, "stopping": default_stopping(60, dtype)}

        def loss(theta):
            g = eqx.tree_at(lambda g: g.factors[0].data, graph, graph.factors[0].data + theta)
            sol = solve(g, linear_solver="schur", **opts)
            return jnp.sum(jnp.asarray(w, dtype) * sol.variables["point"]) + sol.cost

        theta = jnp.zeros_like(graph.factors[0].data)
        return jax.jit(jax.grad(loss), compiler_options=FAST_COMPILE)(theta)

    got, want = ba_gradient(jnp.float32), np.asarray(ba_gradient(jnp.float64))
    assert got.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(got, np.float64), want, rtol=0,
                               atol=3e-4 * np.abs(want).max())


@pytest.mark.slow  # compiles a BA gradient and a BA solve (~15 s)
def test_ba_gradient_matches_finite_differences():
    """``grad`` through a BA solve (the exact Hessian of the reprojection factors in
    closed form, ``_bal_hessian``; Schur elimination) against central differences of the
    solved loss, Richardson-extrapolated, along three random directions."""
    graph, _ = _schur_graph()
    theta = jnp.zeros_like(graph.factors[0].data)
    value = jax.jit(partial(_ba_loss, "schur"), compiler_options=FAST_COMPILE)
    grad = jax.jit(jax.grad(partial(_ba_loss, "schur")), compiler_options=FAST_COMPILE)(theta)
    rng = np.random.default_rng(8)
    for _ in range(3):
        v = jnp.asarray(rng.normal(size=theta.shape))
        along = lambda eps, v=v: float(value(theta + eps * v))  # noqa: E731
        eps = 1e-3
        d1 = (along(eps) - along(-eps)) / (2 * eps)
        d2 = (along(eps / 2) - along(-eps / 2)) / eps
        fd = (4 * d2 - d1) / 3
        assert abs(fd) > 1e-3
        np.testing.assert_allclose(float(jnp.sum(grad * v)), fd, rtol=1e-6)
