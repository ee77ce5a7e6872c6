"""Levenberg–Marquardt on factor graphs: GTSAM's final costs on the reference g2o files,
the three linear solvers agree, status codes, fixed variables, float32.

Reference costs: GTSAM 4.3 LM with the first pose fixed (``conftest.GTSAM_COST``).
Fixed variables and NaN input are checked in ``test_batch.py`` (they reuse its compiled
solver). Initial costs are checked against an independent numpy/scipy evaluation of
``0.5·Σ rᵀΩr``, r = Log(Z⁻¹·Xi⁻¹·Xj).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose import Results, read_g2o, synthetic_pose_graph
from jaxpose.graph import _pgo as pgo
from jaxpose.graph import default_stopping
from jaxpose.optim import Huber

from .conftest import GTSAM_COST, data_file, jit_solve, numpy_pose_graph_cost

DENSE = dict(linear_solver="dense")


def _check_history(sol) -> None:
    k = int(sol.iterations)
    hist = np.asarray(sol.history)
    assert np.all(np.diff(hist[:k]) <= 0), hist[:k]  # only accepted (lower) costs
    assert hist[k - 1] == float(sol.cost) and np.all(np.isnan(hist[k:]))


def test_pose2example_reaches_gtsam_cost():
    pg = read_g2o(data_file("pose2example.txt"))
    problem = pgo.pose_graph_problem(pg)
    sol = jit_solve(**DENSE)(problem)
    assert sol.status_name == "converged" and int(sol.status) == Results.CONVERGED
    np.testing.assert_allclose(float(sol.initial_cost), numpy_pose_graph_cost(pg), rtol=1e-12)
    np.testing.assert_allclose(float(sol.cost), GTSAM_COST["pose2example.txt"], rtol=1e-9)
    poses = np.asarray(sol.variables["pose"].data)
    np.testing.assert_allclose(numpy_pose_graph_cost(pg, poses), float(sol.cost), rtol=1e-12)
    np.testing.assert_array_equal(poses[0], np.asarray(problem.variables["pose"].data)[0])
    _check_history(sol)
    assert int(sol.linear_iterations) == 0  # direct solver


def test_status_max_steps():
    pg = read_g2o(data_file("pose2example.txt"))
    sol = jit_solve(linear_solver="dense", stopping=default_stopping(1))(pgo.pose_graph_problem(pg))
    assert int(sol.status) == Results.MAX_STEPS and sol.status_name == "max_steps"
    assert int(sol.iterations) == 1 and sol.history.shape == (1,)
    assert GTSAM_COST["pose2example.txt"] < float(sol.cost) < float(sol.initial_cost)


@pytest.mark.parametrize("start", ["optimum", "perturbed"])
def test_zero_residual_chain_converges(start):
    # an odometry-only chain fits every measurement exactly: its optimum's cost is
    # rounding noise (~1e-28), where trials can only be rejected; that is convergence,
    # not divergence (it was reported as diverged once the damping hit its bound)
    g, _ = synthetic_pose_graph("SE3", n_poses=8, shape="circle", seed=1)
    odo = np.abs(g.edges[:, 0] - g.edges[:, 1]) == 1
    chain = dataclasses.replace(g, edges=g.edges[odo], measurements=g.measurements[odo],
                                information=g.information[odo])
    poses = np.array(chain.poses)
    if start == "perturbed":
        poses[1:, :3] += 0.3
    sol = jit_solve()(pgo.pose_graph_problem(chain, poses=poses))
    assert sol.status_name == "converged", (sol.status_name, float(sol.cost))
    out = np.asarray(sol.variables["pose"].data)
    assert numpy_pose_graph_cost(chain, out) < 1e-20


def test_float32_pose2example():
    pg = read_g2o(data_file("pose2example.txt"))
    problem = pgo.pose_graph_problem(pg, dtype=jnp.float32)
    sol = jit_solve(**DENSE)(problem)
    assert sol.cost.dtype == jnp.float32 and sol.variables["pose"].data.dtype == jnp.float32
    np.testing.assert_allclose(float(sol.cost), GTSAM_COST["pose2example.txt"], rtol=1e-5)
    # float32 cannot meet the default rtol=1e-10 decrease test, so LM ends when its damping
    # is exhausted (DIVERGED, "stalled", best estimate kept) rather than "converged".
    assert sol.status_name in ("converged", "diverged")
    _check_history(sol)


@pytest.mark.parametrize("solver", ["dense", "sparse"])
def test_float32_solve_factorises_a_stiff_graph_in_float64(solver):
    """Every other edge 1e8 times stiffer than the rest: H's condition passes float32's
    1e7, and a float32 JᵀJ is indefinite, so LM's Cholesky failed at small damping and
    the solve crawled under heavy damping (MAX_STEPS at cost 231.6 dense, 249.5 sparse,
    against 229.96). H is now formed in float64 (x64 on): float32 converges to the float64
    optimum's cost to float32 accuracy."""
    g, _ = synthetic_pose_graph("SE2", n_poses=30, shape="circle", seed=1, noise=(0.05, 0.05))
    info = g.information.copy()
    info[::2] *= 1e8
    g = dataclasses.replace(g, information=info)
    want = jit_solve(linear_solver=solver)(pgo.pose_graph_problem(g))
    sol = jit_solve(linear_solver=solver)(pgo.pose_graph_problem(g, dtype=jnp.float32))
    assert want.status_name == sol.status_name == "converged"
    assert sol.variables["pose"].data.dtype == jnp.float32
    np.testing.assert_allclose(float(sol.cost), float(want.cost), rtol=3e-5)
    poses = np.asarray(sol.variables["pose"].data, np.float64)
    np.testing.assert_allclose(numpy_pose_graph_cost(g, poses), float(want.cost), rtol=3e-5)


# ------------------------------------------------------------------------------------
# SE3 files (one XLA compilation each: slow on a loaded machine)
# ------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("solver", ["dense", "sparse", "pcg"])
def test_tinygrid3d_each_linear_solver_reaches_gtsam_cost(solver):
    pg = read_g2o(data_file("tinyGrid3D.g2o"))
    sol = jit_solve(linear_solver=solver)(pgo.pose_graph_problem(pg))
    assert sol.status_name == "converged"
    np.testing.assert_allclose(float(sol.initial_cost), numpy_pose_graph_cost(pg), rtol=1e-12)
    np.testing.assert_allclose(float(sol.cost), GTSAM_COST["tinyGrid3D.g2o"], rtol=1e-5)
    poses = np.asarray(sol.variables["pose"].data)
    np.testing.assert_allclose(numpy_pose_graph_cost(pg, poses), float(sol.cost), rtol=1e-10)
    _check_history(sol)
    assert (int(sol.linear_iterations) > 0) == (solver == "pcg")


@pytest.mark.slow
def test_pose3example_reaches_gtsam_cost():
    pg = read_g2o(data_file("pose3example.txt"))
    sol = jit_solve(**DENSE)(pgo.pose_graph_problem(pg))
    assert sol.status_name == "converged"
    np.testing.assert_allclose(float(sol.cost), GTSAM_COST["pose3example.txt"], rtol=1e-9)


@pytest.mark.slow
def test_float32_tinygrid3d():
    pg = read_g2o(data_file("tinyGrid3D.g2o"))
    sol = jit_solve(**DENSE)(pgo.pose_graph_problem(pg, dtype=jnp.float32))
    assert sol.cost.dtype == jnp.float32
    np.testing.assert_allclose(float(sol.cost), GTSAM_COST["tinyGrid3D.g2o"], rtol=1e-5)
    poses = np.asarray(sol.variables["pose"].data, np.float64)
    np.testing.assert_allclose(numpy_pose_graph_cost(pg, poses), GTSAM_COST["tinyGrid3D.g2o"],
                               rtol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["smallGrid3D.g2o", "intel.g2o"])
def test_larger_files_reach_gtsam_cost(name):
    pg = read_g2o(data_file(name))
    sol = jax.jit(lambda g: pgo.solve(g, linear_solver="sparse"))(pgo.pose_graph_problem(pg))
    assert sol.status_name == "converged"
    np.testing.assert_allclose(float(sol.cost), GTSAM_COST[name], rtol=1e-5)


@pytest.mark.slow
def test_huber_solve_is_not_pulled_by_an_outlier_edge():
    """A wrong loop closure (3 m off, 30 σ): least squares bends the trajectory towards it;
    with Huber(δ) the estimate stays near the truth and the outlier keeps a large residual."""
    pg, truth = synthetic_pose_graph("SE2", n_poses=12, noise=(0.01, 0.1), seed=6)
    meas = pg.measurements.copy()
    meas[-1, :2] += 3.0
    bad = dataclasses.replace(pg, measurements=meas)
    sols = {}
    for name, kernel in (("plain", None), ("huber", Huber(1.0))):
        sol = jit_solve(**DENSE)(pgo.pose_graph_problem(bad, kernel=kernel))
        assert sol.status_name == "converged", name
        sols[name] = np.asarray(sol.variables["pose"].data)
    err = {k: np.abs(v[:, :2] - truth[:, :2]).max() for k, v in sols.items()}
    assert err["huber"] < 0.5 and err["plain"] > 2 * err["huber"], err
    # the outlier edge's residual: large under Huber (ignored), smaller in least squares
    last = dataclasses.replace(bad, edges=bad.edges[-1:], measurements=meas[-1:],
                               information=bad.information[-1:])
    assert numpy_pose_graph_cost(last, sols["huber"]) > numpy_pose_graph_cost(last, sols["plain"])


def test_repeated_eager_solve_reuses_the_compiled_program():
    """graph.solve is filter_jit-compiled: new values on the same structure never retrace."""
    from jaxpose.graph import Factor, FactorGraph, between_residual, solve
    from jaxpose.lie import SE2

    traces = []

    def counted(xi, xj, z):
        traces.append(1)  # runs only while tracing
        return between_residual(xi, xj, z)

    def graph(noise: float) -> FactorGraph:
        rng = np.random.default_rng(int(noise * 100))
        z = np.tile([1.0, 0.0, 1.0, 0.0], (4, 1))
        z[:, :2] += noise * rng.normal(size=(4, 2))
        poses = np.tile([0.0, 0.0, 1.0, 0.0], (5, 1))
        factor = Factor(counted, [("pose", np.arange(4)), ("pose", np.arange(1, 5))],
                        data=SE2(jnp.asarray(z)))
        return FactorGraph([factor], {"pose": SE2(jnp.asarray(poses))}, fixed={"pose": [0]})

    first = solve(graph(0.1), linear_solver="dense")
    n = len(traces)
    second = solve(graph(0.2), linear_solver="dense")
    assert len(traces) == n  # same structure, new values: no retrace
    assert int(first.status) == Results.CONVERGED and int(second.status) == Results.CONVERGED
    assert float(first.cost) < 1e-20 and float(second.cost) < 1e-20  # a chain fits exactly


def test_graph_and_dense_paths_share_one_iteration(capsys, monkeypatch):
    """graph.solve and least_squares run the same trial (optim._iterate.trial): on one
    SE2 problem with GTSAM's λ-factor rule and Marquardt damping both take the same
    accepted/rejected trials with the same damping, costs and result."""
    from jaxpose.graph import Factor, FactorGraph, prior_residual, solve
    from jaxpose.lie import SE2
    from jaxpose.optim import LM, LambdaFactor, Nielsen, _iterate, least_squares

    paths = []
    trial = _iterate.trial

    def spy(rule, path, *args, **kw):
        paths.append(type(path).__name__)
        return trial(rule, path, *args, **kw)

    monkeypatch.setattr(_iterate, "trial", spy)

    def between(xi, xj, z):  # this test's own residual: a graph structure no other test has
        return z.inv().compose(xi.inv().compose(xj)).log().data

    rng = np.random.default_rng(13)
    n = 7
    truth = np.column_stack([rng.normal(size=(n, 2)) * 3, np.zeros(n), np.ones(n)])
    ang = rng.uniform(-np.pi, np.pi, n)
    truth[:, 2:] = np.column_stack([np.cos(ang), np.sin(ang)])
    edges = np.array([[i, (i + 1) % n] for i in range(n)] + [[0, 3], [2, 5]])
    x_true = SE2(jnp.asarray(truth))
    noise = SE2.exp(jnp.asarray(rng.normal(scale=0.3, size=(len(edges), 3))))
    meas = x_true[edges[:, 0]].inv().compose(x_true[edges[:, 1]]).compose(noise)
    start_ang = ang + rng.normal(scale=3.0, size=n)  # far off: LM rejects some trials
    start = np.column_stack([truth[:, :2] + rng.normal(scale=1.0, size=(n, 2)),
                             np.cos(start_ang), np.sin(start_ang)])
    x0 = SE2(jnp.asarray(start))
    prior = SE2(jnp.asarray(truth[:1]))
    graph = FactorGraph(
        [Factor(between, [("pose", edges[:, 0]), ("pose", edges[:, 1])], data=meas),
         Factor(prior_residual, [("pose", np.array([0]))], data=prior)],
        {"pose": x0},
    )

    def residual(x, args):
        return jnp.concatenate([
            jax.vmap(between)(x[edges[:, 0]], x[edges[:, 1]], meas).reshape(-1),
            jax.vmap(prior_residual)(x[:1], prior).reshape(-1),
        ])

    for strategy in (LambdaFactor(), Nielsen(1e-3)):
        paths.clear()
        stopping = default_stopping(40)
        g = solve(graph, strategy=strategy, stopping=stopping, linear_solver="dense",
                  damping="diagonal", verbose=True)
        jax.effects_barrier()
        g_lines = [ln.split("iter", 1)[1] for ln in capsys.readouterr().out.splitlines()
                   if ln.startswith("graph.solve iter")]
        d = least_squares(residual, x0, None, LM(strategy, diag_min=1e-6, diag_max=1e32),
                          max_steps=stopping.max_steps, cost_rtol=stopping.cost_rtol,
                          gtol=0.0, xtol=0.0, history=True, verbose=True)
        jax.effects_barrier()
        d_lines = [ln.split("iter", 1)[1] for ln in capsys.readouterr().out.splitlines()
                   if ln.startswith("least_squares iter")]
        assert paths == ["_GraphPath", "_DensePath"]  # traced once each, through one core
        k = int(g.iterations)
        assert k == int(d.num_steps) == len(g_lines) == len(d_lines)
        assert int(g.status) == int(d.status) == Results.CONVERGED
        np.testing.assert_allclose(np.asarray(g.history[:k]), np.asarray(d.history[1:k + 1]),
                                   rtol=1e-9)
        accepted = [ln.rsplit("accepted", 1)[1].split()[0] for ln in g_lines]
        assert "False" in accepted and "True" in accepted  # rejections were exercised
        # the same damping before every trial and the same accept/reject decisions
        key = lambda ln: (ln.split("damping")[1].split()[0], ln.split("accepted")[1].split()[0])  # noqa: E731
        assert [key(ln) for ln in g_lines] == [key(ln) for ln in d_lines]
        np.testing.assert_allclose(np.asarray(g.variables["pose"].data),
                                   np.asarray(d.params.data), atol=1e-8)


def test_configuration_objects_check_their_fields():
    """graph.solve's options are objects with named fields; bad values name the field."""
    from jaxpose.graph import PCG, Damping, GraphLinearSolver, default_rtol, solve

    problem = pgo.pose_graph_problem(synthetic_pose_graph("SE2", 4, seed=0)[0])
    assert GraphLinearSolver().resolve(problem) == "dense"  # size 12 <= dense_max 600
    assert GraphLinearSolver(dense_max=10).resolve(problem) == "sparse"
    stop = default_stopping(7, jnp.float32)
    assert (stop.max_steps, stop.cost_rtol, stop.gtol, stop.xtol) == (7, 1e-6, 0.0, 0.0)
    assert default_rtol(jnp.float64) == 1e-10
    with pytest.raises(ValueError, match=r"solve\(linear_solver='qr'\)"):
        solve(problem, linear_solver="qr")
    with pytest.raises(ValueError,
                       match=r"GraphLinearSolver\(dense_max\): expected an int >= 0, got -1"):
        GraphLinearSolver(dense_max=-1)
    with pytest.raises(ValueError, match=r"solve\(damping='lm'\)"):
        Damping("lm")
    with pytest.raises(ValueError, match=r"Damping\(min, max\)"):
        Damping("diagonal", min=1.0, max=0.5)
    with pytest.raises(ValueError, match=r"PCG\(max_iters\): expected an int >= 1, got 0"):
        PCG(max_iters=0)
    with pytest.raises(TypeError, match=r"solve\(linear_solver\): expected a string or "
                                        r"GraphLinearSolver, got int"):
        solve(problem, linear_solver=3)
    with pytest.raises(TypeError, match=r"solve\(cg\): expected a PCG, got float"):
        solve(problem, cg=1e-8)
