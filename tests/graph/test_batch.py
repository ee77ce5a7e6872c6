"""jit + vmap of the factor-graph solver over a batch of pose graphs of equal structure,
and (with the same compiled unbatched solver) fixed variables and NaN input.

One FactorGraph fixes the structure; a vmapped function swaps in each graph's initial
poses and measurements. Every batch member must equal its own unbatched solve (the
while_loop keeps per-member damping and stopping under vmap). The checks that reuse a
compiled solver share one test function: pytest-xdist spreads test functions over
workers, and each worker would compile again.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.datasets import synthetic_pose_graph
from jaxpose.graph import FactorGraph
from jaxpose.graph import _pgo as pgo
from jaxpose.graph import solve as graph_solve

from .conftest import FAST_COMPILE, jit_solve, numpy_pose_graph_cost, with_values

SEEDS = (0, 1, 2, 3, 4)


def _batch():
    pairs = [synthetic_pose_graph("SE2", n_poses=10, noise=(0.02, 0.1), seed=s) for s in SEEDS]
    graphs = [g for g, _ in pairs]
    for g in graphs[1:]:  # equal structure: same edges and information
        np.testing.assert_array_equal(g.edges, graphs[0].edges)
        np.testing.assert_array_equal(g.information, graphs[0].information)
    problems = [pgo.pose_graph_problem(g) for g in graphs]
    poses = np.stack([np.asarray(p.variables["pose"].data) for p in problems])
    meas = np.stack([np.asarray(p.factors[0].data.data) for p in problems])
    return pairs, problems, poses, meas


def _batched(solver: str):
    def run(base, poses, meas):  # base: the graph, a pytree argument (its arrays are traced)
        one = lambda p, m: graph_solve(with_values(base, poses=p, measurements=m),
                                       linear_solver=solver)
        return jax.vmap(one)(poses, meas)

    return jax.jit(run, compiler_options=FAST_COMPILE)


def _check(pairs, sols, singles) -> None:
    for k, ((pg, truth), single) in enumerate(zip(pairs, singles, strict=True)):
        got = jax.tree.map(lambda x, k=k: x[k], sols)
        assert int(got.status) == int(single.status) == 0, k
        assert int(got.iterations) == int(single.iterations), k
        np.testing.assert_allclose(float(got.cost), float(single.cost), rtol=1e-12)
        np.testing.assert_allclose(float(got.initial_cost), float(single.initial_cost),
                                   rtol=1e-12)
        np.testing.assert_allclose(got.variables["pose"].data, single.variables["pose"].data,
                                   rtol=0, atol=1e-10)
        # each solved its own problem: at least as good as the ground truth for that graph
        assert float(got.cost) <= numpy_pose_graph_cost(pg, truth)
        np.testing.assert_allclose(numpy_pose_graph_cost(pg, got.variables["pose"].data),
                                   float(got.cost), rtol=1e-10)
    costs = np.asarray(sols.cost)
    assert len(set(np.round(costs, 12))) == len(SEEDS)  # genuinely different problems


def test_vmap_solve_fixed_variables_and_nan_input():
    pairs, problems, poses, meas = _batch()
    sols = _batched("dense")(problems[0], poses, meas)
    assert sols.cost.shape == (len(SEEDS),)
    assert sols.variables["pose"].data.shape == poses.shape
    single = jit_solve(linear_solver="dense")
    _check(pairs, sols, [single(p) for p in problems])

    # fixed variables: the fixed mask is a leaf, so the compiled solver is reused
    problem, free_sol = problems[0], single(problems[0])
    fixed = [0, 4, 7]
    sol = single(FactorGraph(problem.factors, problem.variables, fixed={"pose": fixed}))
    start = np.asarray(problem.variables["pose"].data)
    out = np.asarray(sol.variables["pose"].data)
    np.testing.assert_array_equal(out[fixed], start[fixed])  # exactly zero steps
    moved = np.setdiff1d(np.arange(len(start)), fixed)
    assert np.all(np.abs(out[moved] - start[moved]).max(1) > 1e-6)
    assert sol.status_name == "converged"
    assert float(free_sol.cost) <= float(sol.cost) < float(sol.initial_cost)

    # NaN in a measurement or an initial pose: a clear error before the first step
    bad_meas = meas[0].copy()
    bad_meas[3, 0] = np.nan
    with pytest.raises(Exception, match="cost is not finite at the initial variables"):
        jax.block_until_ready(single(with_values(problem, measurements=jnp.asarray(bad_meas))))
    bad_poses = poses[0].copy()
    bad_poses[2, 1] = np.inf
    with pytest.raises(Exception, match="cost is not finite at the initial variables"):
        jax.block_until_ready(single(with_values(problem, poses=jnp.asarray(bad_poses))))
    # also where the caller keeps only the cost (XLA drops checks on unused outputs)
    cost_only = jax.jit(lambda p: graph_solve(p, linear_solver="dense").cost,
                        compiler_options=FAST_COMPILE)
    with pytest.raises(Exception, match="cost is not finite at the initial variables"):
        jax.block_until_ready(cost_only(with_values(problem, poses=jnp.asarray(bad_poses))))
    # or only the status (returned NON_FINITE with no error before session 49)
    status_only = jax.jit(lambda p: graph_solve(p, linear_solver="dense").status,
                          compiler_options=FAST_COMPILE)
    with pytest.raises(Exception, match="cost is not finite at the initial variables"):
        jax.block_until_ready(status_only(with_values(problem, poses=jnp.asarray(bad_poses))))


@pytest.mark.slow
def test_vmap_pcg_solve_matches_each_unbatched_solve():
    pairs, problems, poses, meas = _batch()
    sols = _batched("pcg")(problems[0], poses, meas)
    single = jit_solve(linear_solver="pcg")
    _check(pairs, sols, [single(p) for p in problems])
