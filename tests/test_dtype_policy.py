"""A loop's state keeps the dtype of its start (jaxpose/_dtypes.py): float32 states or
variables stepped with float64 data (plain NumPy arrays with x64 on) ran into raw
``while_loop``/``scan`` carry TypeErrors in every solver, filter and controller. Each
case is checked against the same computation in float64, to float32 accuracy."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxpose import control, dynamics, filters, graph, optim, read_g2o
from jaxpose.lie import SE3
from jaxpose.smoothing import FixedLagSmoother

F32 = jnp.float32
LTI = dynamics.LTI(np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]]),
                   np.array([[1.0, 0.0]]))


def test_least_squares_float32_params_with_float64_data():
    x = np.linspace(0, 1, 50)
    data = (x, 3.0 * x + 1.0)

    def res(p, a):
        return (p[0] * a[0] + p[1] - a[1])[:, None]

    for kernel in (None, optim.Huber(np.float64(0.5))):  # a NumPy float64 scale too
        sol = optim.least_squares(res, jnp.zeros(2, F32), data, kernel=kernel)
        assert sol.params.dtype == F32 and sol.status_name == "converged"
        np.testing.assert_allclose(sol.params, [3.0, 1.0], rtol=1e-6)


def test_graph_solve_float32_variables_with_float64_data_and_kernel_scale():
    """tinyGrid3D: float64 measurements and information, float32 poses; a Huber scale
    from np.sqrt(chi2_quantile(...)) (a NumPy float64) made even an all-float32 graph's
    cost float64."""
    from tests.graph.conftest import data_file

    pg = read_g2o(data_file("tinyGrid3D.g2o"))
    c = np.sqrt(graph.chi2_quantile(0.95, 6))

    def solve(pose_dtype, meas_dtype):
        f = graph.Factor(graph.between_residual,
                         [("pose", pg.edges[:, 0]), ("pose", pg.edges[:, 1])],
                         data=SE3(pg.measurements.astype(meas_dtype)),
                         information=pg.information, kernel=optim.Huber(c))
        g = graph.FactorGraph([f], {"pose": SE3(pg.poses.astype(pose_dtype))},
                              fixed={"pose": [0]})
        return graph.solve(g)

    want = solve(np.float64, np.float64)
    for meas in (np.float64, np.float32):
        sol = solve(np.float32, meas)
        assert sol.variables["pose"].data.dtype == F32 and sol.status_name == "converged"
        np.testing.assert_allclose(float(sol.cost), float(want.cost), rtol=1e-5)


def test_rollout_filters_and_lqr_keep_a_float32_state_with_float64_models():
    x0, P0 = jnp.asarray([0.3, -0.2], F32), np.eye(2)
    us = np.tile([[0.5]], (6, 1))
    ys = np.linspace(0.0, 1.0, 6)[:, None]
    xs, _ = dynamics.rollout(LTI, x0, us)
    xs64, _ = dynamics.rollout(LTI, np.asarray(x0, np.float64), us)
    assert xs.dtype == F32
    np.testing.assert_allclose(xs, xs64, rtol=1e-6, atol=1e-7)
    for make in (filters.EKF, filters.UKF):
        f = make(LTI, np.eye(2) * 1e-3, np.eye(1))
        got = f.run(x0, P0, ys, us)
        want = f.run(np.asarray(x0, np.float64), P0, ys, us)
        assert got.x.dtype == F32
        np.testing.assert_allclose(got.x, want.x, rtol=1e-5, atol=1e-6)
    pf = filters.ParticleFilter(LTI, np.eye(2) * 1e-3, np.eye(1), 64)
    got, _ = pf.run(jax.random.PRNGKey(0), x0, P0, ys, us)
    assert got.x.dtype == got.P.dtype == F32  # was float64, silently
    cost = control.QuadraticCost(np.eye(3))
    plan = control.lqr(LTI, cost, x0, 5)
    want = control.lqr(LTI, cost, np.asarray(x0, np.float64), 5)
    assert plan.x.dtype == F32
    np.testing.assert_allclose(plan.x, want.x, rtol=1e-5, atol=1e-6)
    mpc = control.MPC(LTI, cost, 5)(x0)
    assert mpc.x.dtype == F32
    np.testing.assert_allclose(mpc.x, want.x, rtol=1e-5, atol=1e-6)


def test_fixed_lag_smoother_float32_state_with_float64_data():
    """A float32 state with float64 NumPy data (docs/smoothing.md: the packed buffer then
    takes float64) failed inside the elimination's scan; the smoother now keeps its data
    in the state's dtype. Against the same stream in float64."""
    def motion(xp, x, d):
        return (x - xp - d["u"]) / 0.1

    def unary(x, d):
        return x - d["z"]

    def run(dtype):
        sm = FixedLagSmoother(jnp.zeros(2, dtype), {"u": np.ones(2), "z": np.zeros(2)},
                              window=4, motion=motion, unary=unary)
        for t in range(6):
            sm = sm.update(jnp.zeros(2, dtype), {"u": np.ones(2), "z": np.full(2, 0.9 * t)})
        return sm

    got, want = run(F32), run(jnp.float64)
    assert got.latest().dtype == F32 and got.status_name == "converged"
    np.testing.assert_allclose(got.latest(), want.latest(), rtol=1e-5)
