"""Full float32 matrix products in jaxpose's programs, on every backend.

JAX lets GPUs (TF32) and TPUs (bfloat16 passes) multiply float32 matrices to about three
significant digits by default; measured on an H100, that made a float32 ``covariance`` 0.6 %
wrong and ``small_matmul``'s fallback 0.2 % wrong. jaxpose traces its entry points, and the
derivative rules traced later, under ``jax.default_matmul_precision("float32")``
(:mod:`jaxpose._precision`). The CPU ignores the setting, so these tests read the traced
programs: every ``dot_general`` in them, derivatives included, must ask for full precision.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _jaxprs import equations

from jaxpose.control import QuadraticCost, lqr
from jaxpose.datasets import synthetic_pose_graph
from jaxpose.dynamics import LTI
from jaxpose.graph import marginals, pose_graph_problem
from jaxpose.graph import solve as graph_solve
from jaxpose.lie._base import small_matmul
from jaxpose.optim import covariance, least_squares

F32 = jnp.float32
FULL = jax.lax.Precision.HIGHEST


def _assert_full(fn: Any, *args: Any) -> int:
    """All float32 dot_generals of ``make_jaxpr(fn)(*args)`` at full precision; returns
    how many there are (a test that finds none checks nothing)."""
    dots = [e for e in equations(jax.make_jaxpr(fn)(*args).jaxpr)
            if e.primitive.name == "dot_general" and any(v.aval.dtype == F32 for v in e.invars)]
    reduced = [e for e in dots if e.params["precision"] is None
               or any(p != FULL for p in e.params["precision"])]
    assert not reduced, f"{len(reduced)} of {len(dots)} float32 products at reduced precision: " \
                        f"{[str(e.params['precision']) for e in reduced[:3]]}"
    return len(dots)


def _linear(params, args):
    a, b = args
    return a @ params - b


def _lsq_args():
    rng = np.random.default_rng(0)
    return jnp.zeros(4, F32), (jnp.asarray(rng.normal(size=(8, 4)), F32),
                               jnp.asarray(rng.normal(size=8), F32))


def test_least_squares_and_covariance_values_and_derivatives():
    x0, args = _lsq_args()
    assert _assert_full(lambda a: least_squares(_linear, x0, a).params, args) > 0
    loss = lambda a: jnp.sum(least_squares(_linear, x0, a).params ** 2)
    assert _assert_full(jax.grad(loss), args) > 0
    assert _assert_full(lambda a: covariance(_linear, x0, a), args) > 0
    assert _assert_full(jax.grad(lambda a: jnp.trace(covariance(_linear, x0, a))), args) > 0


@pytest.mark.parametrize("linear_solver", ["dense", pytest.param("pcg", marks=pytest.mark.slow)])
def test_graph_solve_marginals_and_the_implicit_gradient(linear_solver):
    pg, _ = synthetic_pose_graph("SE2", n_poses=6, noise=(0.02, 0.1), seed=0)
    graph = pose_graph_problem(pg, dtype=F32)
    assert _assert_full(lambda g: graph_solve(g, linear_solver=linear_solver).cost, graph) > 0
    sol = graph_solve(graph, linear_solver="dense")
    assert _assert_full(lambda g: marginals(g, sol, "pose").covariances["pose"], graph) > 0

    def loss(meas):
        g = eqx.tree_at(lambda g: g.factors[0].data.data, graph, meas)
        return graph_solve(g, linear_solver=linear_solver).cost

    assert _assert_full(jax.grad(loss), graph.factors[0].data.data) > 0


def test_lqr_value_and_gradient():
    n, m, T = 3, 2, 5
    rng = np.random.default_rng(1)
    A = jnp.asarray(np.eye(n) + 0.1 * rng.normal(size=(n, n)), F32)
    B = jnp.asarray(rng.normal(size=(n, m)), F32)
    cost = QuadraticCost(jnp.eye(n + m, dtype=F32))
    x0 = jnp.ones(n, F32)
    assert _assert_full(lambda a: lqr(LTI(a, B), cost, x0, T).u, A) > 0
    assert _assert_full(jax.grad(lambda a: jnp.sum(lqr(LTI(a, B), cost, x0, T).u ** 2)), A) > 0


def test_small_matmul_fallback_and_the_checker_itself():
    a = jnp.ones((2, 20, 20), F32)
    assert _assert_full(small_matmul, a, a) == 1
    # the checker fails on a product at the default precision
    with pytest.raises(AssertionError, match="1 of 1 float32 products at reduced precision"):
        _assert_full(lambda x: x @ x, a)


def test_geometry_imu_and_smoother_entry_points():
    from jaxpose.geometry import epnp, icp, point2pixel, umeyama
    from jaxpose.imu import preintegrate
    from jaxpose.lie import SE3

    rng = np.random.default_rng(2)
    src = jnp.asarray(rng.normal(size=(40, 3)), F32)
    pose = SE3.exp(jnp.asarray([0.1, -0.2, 0.3, 0.05, 0.1, -0.1], F32))
    tgt = pose.act(src)
    assert _assert_full(lambda s: icp(s, tgt, max_iterations=3).transform.data, src) > 0
    assert _assert_full(lambda s: umeyama(s, tgt).data, src) > 0
    K = jnp.asarray([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]], F32)
    pw = src + jnp.asarray([0, 0, 6.0], F32)
    uv = point2pixel(pw, K, pose)
    assert _assert_full(lambda p: epnp(p, uv, K).transform.data, pw) > 0
    g = jnp.asarray(rng.normal(size=(20, 3)) * 0.1, F32)
    assert _assert_full(lambda a: preintegrate(g, a, jnp.full(20, 0.01, F32), gyro_noise=1e-3,
                                               acc_noise=1e-2).cov, g) > 0


def test_filter_step_api_box_qp_and_riccati():
    """The documented step-by-step filter methods (what docs/pypose-migration.md has
    users call for PyPose-timed data) and the public control building blocks, not only
    the ``run``/``step`` drivers."""
    from jaxpose.control import box_qp, lq_problem, riccati
    from jaxpose.filters import EKF, UKF, ParticleFilter

    n = 3
    model = LTI(jnp.eye(n, dtype=F32) * 0.9, jnp.ones((n, 1), F32))
    x, P = jnp.ones(n, F32), jnp.eye(n, dtype=F32)
    y, u = jnp.ones(n, F32), jnp.zeros(1, F32)
    for filt in (EKF(model, 0.1 * P, 0.2 * P), UKF(model, 0.1 * P, 0.2 * P)):
        assert _assert_full(lambda x: filt.predict(x, P, u)[1], x) > 0
        assert _assert_full(lambda x: filt.update(x, P, y, u)[1], x) > 0
    pf = ParticleFilter(model, 0.1 * P, 0.2 * P, num_particles=8)
    key = jax.random.PRNGKey(0)
    assert _assert_full(lambda p: pf.init(key, x, p).particles, P) > 0
    state = pf.init(key, x, P)
    assert _assert_full(lambda s: pf.estimate(s)[1], state) > 0
    H = jnp.asarray([[2.0, 0.5], [0.5, 1.0]], F32)
    lo, hi = jnp.full(2, -1.0, F32), jnp.ones(2, F32)
    assert _assert_full(lambda g: box_qp(H, g, lo, hi, jnp.zeros(2, F32)).x,
                        jnp.ones(2, F32)) > 0
    problem = lq_problem(model, QuadraticCost(jnp.eye(n + 1, dtype=F32)), 4)
    assert _assert_full(lambda F: riccati(F, *problem[1:])[0], problem[0]) > 0
