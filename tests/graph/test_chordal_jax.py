"""The chordal relaxation in JAX (jaxpose.graph.chordal_poses / initial_variables) against
the host relaxation (NumPy, SciPy/CHOLMOD: other assembly, SVD projection, Cholesky square
roots), the truth of noise-free graphs, finite differences, and under jit and vmap."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose import read_g2o
from jaxpose.datasets import synthetic_pose_graph
from jaxpose.graph import (
    Factor,
    FactorGraph,
    between_residual,
    chordal_initialization,
    chordal_poses,
    initial_poses,
    initial_variables,
    optimize_pose_graph,
    pose_graph_problem,
    prior_residual,
    solve,
)
from jaxpose.graph._pgo import solve_from_start, start_in_solve
from jaxpose.io import PoseGraph
from jaxpose.lie import SE3

from .conftest import FAST_COMPILE, _pose_matrix, data_file


def _graph(kind: str, n: int = 30, seed: int = 0,
           noise=(0.02, 0.05)) -> tuple[PoseGraph, np.ndarray]:
    """A grid graph with noisy odometry start and full, anisotropic information matrices
    (eigenvalues spread over three decades: some rotation blocks have λ_max > ½·trace,
    which the relaxation clips)."""
    graph, truth = synthetic_pose_graph(kind, n_poses=n, noise=noise, seed=seed, shape="grid")
    rng = np.random.default_rng(seed)
    t = graph.information.shape[1]
    q, _ = np.linalg.qr(rng.normal(size=(graph.n_edges, t, t)))
    w = 10.0 ** rng.uniform(-1, 2, size=(graph.n_edges, t))
    info = q @ (w[..., None] * np.swapaxes(q, 1, 2))
    return dataclasses.replace(graph, information=0.5 * (info + np.swapaxes(info, 1, 2))), truth


def _pose_error(kind: str, a, b) -> float:
    """Largest entry of |A⁻¹·B − I| over the poses (independent of the quaternion sign)."""
    eye = np.eye(3 if kind == "SE2" else 4)
    return max(np.abs(np.linalg.inv(_pose_matrix(kind, p)) @ _pose_matrix(kind, q) - eye).max()
               for p, q in zip(np.asarray(a), np.asarray(b), strict=True))


def _jax_chordal(graph: PoseGraph, dtype=jnp.float64) -> np.ndarray:
    return np.asarray(jax.jit(chordal_poses)(pose_graph_problem(graph, dtype=dtype))["pose"].data)


@pytest.mark.parametrize("kind", ["SE3", "SE2"])
def test_matches_the_host_relaxation_with_full_information(kind):
    graph, _ = _graph(kind)
    o_rr = graph.information[:, 3:, 3:] if kind == "SE3" else None
    if o_rr is not None:  # the clipping branch of the rotation weights is exercised
        assert np.any(np.linalg.eigvalsh(o_rr)[:, -1] > 0.5 * np.trace(o_rr, axis1=1, axis2=2))
    host = chordal_initialization(graph)
    assert _pose_error(kind, host, graph.poses) > 1e-2  # the relaxation moved the poses
    assert _pose_error(kind, _jax_chordal(graph), host) < 1e-9


@pytest.mark.parametrize("kind", ["SE3", "SE2"])
def test_noise_free_graph_recovered_exactly(kind):
    """Noise-free measurements, far-off start: the relaxation is tight, the truth comes back
    (the gauge: pose 0 is the true pose)."""
    graph, truth = _graph(kind, noise=(0.0, 0.0))
    start = truth.copy()
    start[1:] = synthetic_pose_graph(kind, n_poses=30, seed=7, shape="grid")[1][1:]
    graph = dataclasses.replace(graph, poses=start)
    assert _pose_error(kind, graph.poses, truth) > 0.1
    assert _pose_error(kind, _jax_chordal(graph), truth) < 1e-9


@pytest.mark.parametrize("name", ["pose2example.txt", "pose3example.txt", "tinyGrid3D.g2o"])
def test_shared_graphs_match_the_host(name):
    graph = read_g2o(data_file(name))
    assert _pose_error(graph.kind, _jax_chordal(graph), chordal_initialization(graph)) < 1e-9


def test_vmap_over_graphs_of_one_structure_matches_one_by_one():
    graphs = [_graph("SE3", n=12, seed=s)[0] for s in range(3)]
    problems = [pose_graph_problem(g) for g in graphs]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *problems)
    out = jax.jit(jax.vmap(chordal_poses))(batch)["pose"].data
    for k, g in enumerate(graphs):
        assert _pose_error("SE3", out[k], chordal_initialization(g)) < 1e-9


def test_a_batch_of_graphs_initialises_and_solves_in_one_program():
    graphs = [_graph("SE2", n=9, seed=s)[0] for s in range(3)]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *[pose_graph_problem(g) for g in graphs])
    # the pattern of docs/graph.md, with the public functions
    sols = jax.jit(jax.vmap(lambda p: solve(p, initial_variables(p)[0])))(batch)
    assert np.all(np.asarray(jax.vmap(lambda p: initial_variables(p)[1])(batch)))
    for k, g in enumerate(graphs):
        host = solve(pose_graph_problem(g, poses=initial_poses(g, "auto")[0]))
        np.testing.assert_allclose(float(sols.cost[k]), float(host.cost), rtol=1e-10)
        assert _pose_error("SE2", sols.variables["pose"].data[k],
                           host.variables["pose"].data) < 1e-7


def test_float32_follows_float64():
    graph, _ = _graph("SE3", n=16)
    f32 = _jax_chordal(graph, jnp.float32)
    assert f32.dtype == np.float32 and np.isfinite(f32).all()
    assert _pose_error("SE3", f32, _jax_chordal(graph)) < 2e-4


def test_derivative_matches_finite_differences():
    """d(Σ chordal translations)/d(measurements): autodiff against central differences
    (first and second order along one direction)."""
    graph, _ = _graph("SE3", n=8, noise=(0.05, 0.1))
    problem = pose_graph_problem(graph)
    z0 = problem.factors[0].data.data
    direction = jnp.asarray(np.random.default_rng(3).normal(size=z0.shape)) * jnp.concatenate(
        [jnp.ones(3), jnp.zeros(4)])  # translations of the measurements

    def f(eps):
        p = eqx.tree_at(lambda q: q.factors[0].data.data, problem, z0 + eps * direction)
        return jnp.sum(chordal_poses(p)["pose"].data[:, :3] ** 2)

    h, f_at = 1e-5, jax.jit(f)
    d1 = float(jax.jit(jax.jacfwd(f))(0.0))
    fd1 = (float(f_at(h)) - float(f_at(-h))) / (2 * h)
    np.testing.assert_allclose(d1, fd1, rtol=1e-6)
    d2 = float(jax.jit(jax.jacfwd(jax.grad(f)))(0.0))
    fd2 = (float(f_at(1e-3)) - 2 * float(f_at(0.0)) + float(f_at(-1e-3))) / 1e-6
    np.testing.assert_allclose(d2, fd2, rtol=1e-4)


def test_auto_takes_the_lower_cost_like_the_host():
    graph, _ = _graph("SE2", n=20)
    _, used = jax.jit(initial_variables)(pose_graph_problem(graph))
    assert bool(used) and initial_poses(graph, "auto")[1] == "chordal"
    # a file that holds the optimum costs less than the relaxation: kept
    optimum, _ = optimize_pose_graph(graph, init="chordal")
    graph = dataclasses.replace(graph, poses=optimum)
    start, used = jax.jit(initial_variables)(pose_graph_problem(graph))
    assert not bool(used) and initial_poses(graph, "auto")[1] == "odometry"
    np.testing.assert_array_equal(np.asarray(start["pose"].data),
                                  np.asarray(pose_graph_problem(graph).variables["pose"].data))
    odo, used = initial_variables(pose_graph_problem(graph), "odometry")
    assert not bool(used)


def test_a_rotation_left_free_by_its_weights_takes_the_ridge_like_the_host():
    """A chain whose last pose hangs on one edge with Ω_R = diag(1, 1, 2): the rotation
    weight ½·tr(Ω_R)·I − Ω_R = diag(1, 1, 0) leaves a row of that pose's rotation
    unconstrained, so the normal matrix is singular and both versions take the ridge."""
    graph, _ = synthetic_pose_graph("SE3", n_poses=10, noise=(0.02, 0.05), seed=2)
    chain = np.abs(graph.edges[:, 1] - graph.edges[:, 0]) == 1
    info = graph.information[chain].copy()
    info[-1] = np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 2.0])
    graph = dataclasses.replace(graph, edges=graph.edges[chain],
                                measurements=graph.measurements[chain], information=info)
    assert graph.edges[-1].tolist() == [8, 9]
    host, ours = chordal_initialization(graph), _jax_chordal(graph)
    assert np.isfinite(ours).all()
    assert _pose_error("SE3", ours, host) < 1e-6


def test_derivative_through_the_ridge_retry_matches_finite_differences():
    """A valid information matrix that knows yaw far better than roll and pitch leaves that
    pose's normal matrix singular, so the solve retries with a ridge. Reverse mode sent the
    discarded first solve's zero cotangent through its NaN Cholesky factor: the gradient's
    last three entries were NaN (also under vmap) while jacfwd and differences agreed."""

    def build(eta):
        z = SE3.exp(jnp.stack([jnp.array([1.0, 0.1, 0.0, 0.05, 0.02, 0.1]),
                               jnp.array([0.9, -0.1, 0.1, 0.1, -0.05, 0.2]) + eta]))
        info = jnp.stack([jnp.eye(6), jnp.diag(jnp.array([1.0, 1, 1, 1, 2, 100]))])
        f = Factor(between_residual, [("pose", np.array([0, 1])), ("pose", np.array([1, 2]))],
                   data=z, information=info)
        return FactorGraph([f], {"pose": SE3.exp(jnp.full((3, 6), 0.01))},
                           fixed={"pose": [0]})

    weights = jnp.asarray(np.random.default_rng(0).normal(size=(3, 7)))

    def f(eta):
        return jnp.sum(chordal_poses(build(eta))["pose"].data * weights)

    eta = jnp.array([0.01, 0.02, -0.01, 0.03, 0.0, 0.01])
    h, f_at = 1e-5, jax.jit(f)
    fd = [(float(f_at(eta.at[k].add(h))) - float(f_at(eta.at[k].add(-h)))) / (2 * h)
          for k in range(6)]
    grad = jax.jit(jax.grad(f))(eta)
    np.testing.assert_allclose(grad, fd, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(jax.jacfwd(f)(eta), grad, rtol=1e-12)
    batch = jnp.stack([eta, 2 * eta])
    lanes = jax.jit(jax.vmap(jax.grad(f)))(batch)
    np.testing.assert_allclose(lanes[0], grad, rtol=1e-12)
    np.testing.assert_allclose(lanes[1], jax.grad(f)(batch[1]), rtol=1e-12)


def test_optimize_pose_graph_initialises_in_the_solve_like_the_host():
    graph, _ = _graph("SE3", n=9)
    assert start_in_solve(graph, "auto") and not start_in_solve(graph, "odometry")
    poses, sol = optimize_pose_graph(graph)
    host = solve(pose_graph_problem(graph, poses=initial_poses(graph, "auto")[0]))
    np.testing.assert_allclose(float(sol.cost), float(host.cost), rtol=1e-10)
    assert _pose_error("SE3", poses, host.variables["pose"].data) < 1e-7
    # differentiable: the derivative of the solution does not depend on the start
    problem = pose_graph_problem(graph)

    def loss(p, in_solve):
        if in_solve:
            return jnp.sum(solve_from_start(p, "auto")[0].variables["pose"].data[:, :3])
        start = pose_graph_problem(graph, poses=initial_poses(graph, "auto")[0]).variables
        return jnp.sum(solve(p, start).variables["pose"].data[:, :3])

    def grad_info(in_solve):
        grad = jax.grad(lambda s: loss(
            eqx.tree_at(lambda q: q.factors[0].sqrt_info, problem, s), in_solve))
        return jax.jit(grad, compiler_options=FAST_COMPILE)(problem.factors[0].sqrt_info)

    np.testing.assert_allclose(grad_info(True), grad_info(False), rtol=1e-7, atol=1e-12)


def test_bad_input_is_refused_with_a_clear_message():
    with pytest.raises(TypeError, match=r"chordal_poses\(graph\): expected a FactorGraph"):
        chordal_poses({"pose": None})
    graph = _graph("SE3", n=4)[0]
    prior = Factor(prior_residual, [("pose", np.arange(4))], data=SE3.identity((4,)))
    with pytest.raises(ValueError, match="expected a pose graph"):
        chordal_poses(FactorGraph([prior], pose_graph_problem(graph).variables))
    big, _ = synthetic_pose_graph("SE3", n_poses=101, seed=0)
    with pytest.raises(ValueError, match="at most DENSE_MAX = 600.*chordal_initialization"):
        chordal_poses(pose_graph_problem(big))
    assert not start_in_solve(big, "auto")
    free = pose_graph_problem(_graph("SE2", n=4)[0], fix="none")
    with pytest.raises(Exception, match="no pose is held"):
        jax.block_until_ready(jax.jit(chordal_poses)(free))
    assert not start_in_solve(_graph("SE2", n=4)[0], "auto", fix="none")
    with pytest.raises(ValueError, match=r"initial_variables\(init='spanning'\)"):
        initial_variables(pose_graph_problem(_graph("SE2", n=4)[0]), "spanning")
