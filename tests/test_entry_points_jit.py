"""Every public entry point is compiled on first call: a second call with new data of the
same shapes does not trace again (so it does not recompile), a call with new shapes does.

Each test wraps a helper that the entry point calls only while its body runs in Python
(i.e. while tracing, once it is compiled) and counts those calls. Without compilation the
body, and so the helper, would run on every call.
"""

from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose import Results
from jaxpose.control import LQR, MPC, QuadraticCost, closed_loop, ilqr, lqr, lqr_solve
from jaxpose.dynamics import LTI, Pendulum
from jaxpose.geometry import epnp, icp, point2pixel
from jaxpose.imu import preintegrate
from jaxpose.lie import SE3

jax.config.update("jax_enable_x64", True)

# the modules themselves (``jaxpose.control.lqr`` etc. are shadowed by the functions)
lqr_mod, ilqr_mod, mpc_mod, icp_mod, pnp_mod, imu_core = (
    importlib.import_module(f"jaxpose.{name}")
    for name in ("control._lqr", "control._ilqr", "control._mpc", "geometry._icp",
                 "geometry._pnp", "imu._core")
)


def counter(monkeypatch, module, name):
    """Replace ``module.name`` by a wrapper that records each call; returns the record."""
    calls = []
    original = getattr(module, name)

    def wrapped(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, wrapped)
    return calls


def assert_traced_once(calls, first, again, reshaped):
    """``first()`` may trace (or hit a cache of an earlier test); ``again()`` (new values,
    same shapes) must not; ``reshaped()`` (new shapes) must."""
    first()
    calls.clear()
    again()
    assert not calls, f"retraced {len(calls)} time(s) for new data of the same shapes"
    reshaped()
    assert calls, "new shapes must trace (the counter is hooked into the traced body)"


def lq_system(rng, n=2, m=1):
    A = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    B = rng.normal(size=(n, m))
    cost = QuadraticCost(np.eye(n + m) + 0.1 * np.ones((n + m, n + m)), QT=np.eye(n))
    return LTI(A, B), cost


def test_lqr_solve_and_lqr_compile_once(monkeypatch, rng=np.random.default_rng(0)):
    T, n, m = 7, 3, 2
    F = rng.normal(size=(T, n, n + m)) * 0.3
    f = rng.normal(size=(T, n))
    C = np.tile(np.eye(n + m), (T, 1, 1))
    c = rng.normal(size=(T, n + m))
    calls = counter(monkeypatch, lqr_mod, "riccati")
    assert_traced_once(
        calls,
        lambda: lqr_solve(F, f, C, c, np.ones(n)),
        lambda: lqr_solve(F + 0.01, 2 * f, C, -c, rng.normal(size=n)),
        lambda: lqr_solve(F[:-1], f[:-1], C[:-1], c[:-1], np.ones(n)),
    )
    # the result of a compiled call equals an eager run of the same code
    sol = lqr_solve(F, f, C, c, np.ones(n))
    with jax.disable_jit():
        ref = lqr_solve(F, f, C, c, np.ones(n))
    np.testing.assert_allclose(sol.x, ref.x, rtol=1e-12, atol=1e-12)

    calls = counter(monkeypatch, lqr_mod, "lq_problem")
    system, cost = lq_system(rng)
    system2, _ = lq_system(rng)  # new matrices, same shapes: traced, not static
    assert_traced_once(
        calls,
        lambda: lqr(system, cost, np.ones(2), 6),
        lambda: lqr(system2, cost, np.array([0.5, -1.0]), 6),
        lambda: lqr(system, cost, np.ones(2), 5),  # horizon is static
    )


def test_lqr_module_compiles_once(monkeypatch, rng=np.random.default_rng(1)):
    system, cost = lq_system(rng)
    module, module2 = LQR(system, cost, 8), LQR(lq_system(rng)[0], cost, 8)
    calls = counter(monkeypatch, lqr_mod, "lq_problem")
    assert_traced_once(
        calls,
        lambda: module(np.ones(2)),
        lambda: module2(np.array([3.0, 0.1])),
        lambda: module(np.ones((4, 2))),
    )


def test_ilqr_compiles_once_and_checks_stay_eager(monkeypatch):
    # Python floats in a module are static fields under filter_jit (a new value compiles
    # anew); arrays are traced
    model = Pendulum(dt=0.1, length=jnp.asarray(1.0))
    cost = QuadraticCost(np.diag([1.0, 0.1, 0.01]), QT=10 * np.eye(2))
    calls = counter(monkeypatch, ilqr_mod, "backward_step")
    assert_traced_once(
        calls,
        lambda: ilqr(model, cost, np.array([0.3, 0.0]), np.zeros((9, 1)), u_lower=-1.0,
                     u_upper=1.0, max_iter=20),
        lambda: ilqr(Pendulum(dt=0.1, length=jnp.asarray(1.3)), cost, np.array([-0.2, 0.1]),
                     np.full((9, 1), 0.1), u_lower=-0.5, u_upper=2.0, max_iter=20, t0=4),
        lambda: ilqr(model, cost, np.array([0.3, 0.0]), np.zeros((10, 1)), u_lower=-1.0,
                     u_upper=1.0, max_iter=20),
    )
    # value checks on the limits still raise (they run before the compiled solve)
    with pytest.raises(ValueError, match="u_lower, u_upper"):
        ilqr(model, cost, np.zeros(2), np.zeros((9, 1)), u_lower=1.0, u_upper=0.0)
    with pytest.raises(ValueError, match="u_lower: contains NaN"):
        ilqr(model, cost, np.zeros(2), np.zeros((9, 1)), u_lower=np.nan)


def test_mpc_call_and_closed_loop_compile_once(monkeypatch, rng=np.random.default_rng(2)):
    system, cost = lq_system(rng)
    mpc = MPC(system, cost, 6, u_lower=-1.0, u_upper=1.0, max_iter=30)
    mpc2 = MPC(lq_system(rng)[0], cost, 6, u_lower=-2.0, u_upper=0.5, max_iter=30)
    calls = counter(monkeypatch, mpc_mod, "_solve")
    assert_traced_once(
        calls,
        lambda: mpc(np.ones(2)),
        lambda: mpc2(np.array([-0.4, 2.0]), np.full((6, 1), 0.2)),
        lambda: mpc(np.ones((3, 2))),
    )
    sol = mpc(np.ones(2))
    assert sol.status_name == "converged" and np.all(np.abs(sol.u) <= 1.0 + 1e-12)
    # gradients flow through the compiled call
    g = jax.grad(lambda x: mpc(x).cost)(jnp.ones(2))
    assert g.shape == (2,) and np.all(np.isfinite(g))

    # closed_loop's own body (its check runs at trace time only once compiled)
    calls = counter(monkeypatch, mpc_mod, "check_count")
    assert_traced_once(
        calls,
        lambda: closed_loop(mpc, system, np.ones(2), 5),
        lambda: closed_loop(mpc2, system, np.array([0.2, -0.3]), 5),
        lambda: closed_loop(mpc, system, np.ones(2), 4),  # steps is static
    )


K = np.array([[520.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def _pnp_scene(rng, batch, n=8):
    pw = rng.uniform(-1, 1, size=(batch, n, 3))
    pose = SE3.exp(jnp.asarray(np.c_[rng.normal(size=(batch, 2)) * 0.2,
                                     rng.uniform(4, 6, (batch, 1)),
                                     rng.normal(size=(batch, 3)) * 0.2]))
    return pw, np.asarray(point2pixel(pw, K, pose))


def test_epnp_compiles_once(monkeypatch, rng=np.random.default_rng(3)):
    (pw, uv), (pw2, uv2), (pw3, uv3) = (_pnp_scene(rng, 2), _pnp_scene(rng, 2),
                                        _pnp_scene(rng, 2, n=9))
    calls = counter(monkeypatch, pnp_mod, "_epnp_single")
    assert_traced_once(
        calls,
        lambda: epnp(pw, uv, K, refine=False),
        lambda: epnp(pw2, uv2, K, refine=False),
        lambda: epnp(pw3, uv3, K, refine=False),
    )
    res = epnp(pw2, uv2, K, refine=False)
    np.testing.assert_array_equal(res.status, Results.CONVERGED)
    assert list(res.status_name) == ["converged", "converged"]


def test_icp_compiles_once(monkeypatch, rng=np.random.default_rng(4)):
    src = rng.uniform(-1, 1, size=(60, 3)) * np.array([2.0, 1.0, 0.5])
    motion = SE3.exp(jnp.array([0.05, -0.02, 0.03, 0.02, 0.05, -0.03]))
    tgt = np.asarray(motion.act(src))
    calls = counter(monkeypatch, icp_mod, "_icp_single")
    assert_traced_once(
        calls,
        lambda: icp(src, tgt, max_iterations=30),
        lambda: icp(src + 0.01, tgt * 1.01, max_iterations=20, tolerance=1e-8),
        lambda: icp(src[:50], tgt, max_iterations=30),
    )


def test_preintegrate_compiles_once(monkeypatch, rng=np.random.default_rng(5)):
    g, a = rng.normal(size=(2, 20, 3)) * 0.1, rng.normal(size=(2, 20, 3))
    calls = counter(monkeypatch, imu_core, "window")
    assert_traced_once(
        calls,
        lambda: preintegrate(g[0], a[0], np.full(20, 0.01), gyro_noise=1e-3, acc_noise=1e-2),
        lambda: preintegrate(g[1], a[1], np.full(20, 0.02), gyro_noise=2e-3, acc_noise=1e-3),
        lambda: preintegrate(g[0, :10], a[0, :10], np.full(10, 0.01), gyro_noise=1e-3,
                             acc_noise=1e-2),
    )


def _pose_graph(seed, n):
    """A small synthetic SE3 pose graph as a FactorGraph (first pose fixed)."""
    from jaxpose import synthetic_pose_graph
    from jaxpose.graph import pose_graph_problem

    return pose_graph_problem(synthetic_pose_graph("SE3", n_poses=n, seed=seed)[0])


def test_marginals_compile_once(monkeypatch):
    import scipy.sparse

    from jaxpose.graph import marginals

    marg_mod = importlib.import_module("jaxpose.graph._marginals")
    g4, g4b, g5 = _pose_graph(0, 4), _pose_graph(1, 4), _pose_graph(0, 5)
    calls = counter(monkeypatch, marg_mod, "linearize")
    assert_traced_once(
        calls,
        lambda: marginals(g4, None, "pose"),
        lambda: marginals(g4b, None, "pose"),
        lambda: marginals(g5, None, "pose"),
    )
    # the compiled result is the inverse of H with the fixed first pose held (identity rows)
    st = g4b.structure
    lin = marg_mod.linearize(g4b, g4b.variables)
    data = np.asarray(marg_mod.csr_values(g4b, lin).at[st.diag_pos].add(
        1.0 - np.repeat(np.asarray(st.free[0]), 6)))
    H = scipy.sparse.csr_matrix((data, np.asarray(st.csr_indices), np.asarray(st.csr_indptr)))
    cov = np.linalg.inv(H.toarray())
    out = marginals(g4b, None, "pose", method="dense").covariances["pose"]
    for k in range(1, 4):
        np.testing.assert_allclose(np.asarray(out[k]), cov[6 * k:6 * k + 6, 6 * k:6 * k + 6],
                                   rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(out[0]), 0.0)  # the fixed pose


def test_covariance_compiles_once(monkeypatch, rng=np.random.default_rng(7)):
    from jaxpose.optim import covariance

    cov_mod = importlib.import_module("jaxpose.optim._covariance")
    calls = counter(monkeypatch, cov_mod, "as_problem")

    def res(p, a):
        return jnp.r_[p - a, 0.5 * p[:1] * p[1:]]

    a1, a2, a3 = rng.normal(size=3), rng.normal(size=3), rng.normal(size=4)
    assert_traced_once(
        calls,
        lambda: covariance(res, jnp.asarray(a1), jnp.asarray(a1)),
        lambda: covariance(res, jnp.asarray(a2), jnp.asarray(a2)),
        lambda: covariance(res, jnp.asarray(a3), jnp.asarray(a3)),
    )
    # against (JᵀJ)⁻¹ with the Jacobian written out by hand
    p = np.asarray(a2)
    J = np.r_[np.eye(3), np.c_[0.5 * p[1:, None], 0.5 * p[0] * np.eye(2)]]
    np.testing.assert_allclose(np.asarray(covariance(res, jnp.asarray(p), jnp.asarray(p))),
                               np.linalg.inv(J.T @ J), rtol=1e-10)


def test_filters_compile_once(monkeypatch, rng=np.random.default_rng(8)):
    """EKF/UKF/PF ``step`` and ``run`` compile on first call; a Python loop over time
    steps (``t`` a Python int) reuses the program."""
    from jaxpose.filters import EKF, UKF, ParticleFilter

    A, B = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]])
    model = LTI(A, B, C=np.eye(2), D=np.zeros((2, 1)))
    x0, P0 = jnp.zeros(2), jnp.eye(2)
    ys, us = rng.normal(size=(6, 2)), rng.normal(size=(6, 1))
    for cls in (EKF, UKF):
        filt = cls(model, Q=np.eye(2) * 1e-2, R=np.eye(2) * 0.1)
        calls = counter(monkeypatch, cls, "_step")
        assert_traced_once(
            calls,
            lambda f=filt: f.run(x0, P0, ys, us),
            lambda f=filt: f.run(x0 + 1.0, P0 * 2.0, ys + 1.0, us, t0=3),
            lambda f=filt: f.run(x0, P0, ys[:4], us[:4]),
        )
        filt.step(x0, P0, ys[0], us[0], t=0)
        calls.clear()
        x, P = x0, P0
        for t in range(1, 4):
            x, P = filt.step(x, P, ys[t], us[t], t=t)
        assert not calls, f"{cls.__name__}.step retraced in a loop over t"
        ref = filt.run(x0, P0, ys[:4], us[:4])  # the same recursion by scan
        x, P = x0, P0
        for t in range(4):
            x, P = filt.step(x, P, ys[t], us[t], t=t)
        np.testing.assert_allclose(np.asarray(x), np.asarray(ref.x[-1]), rtol=1e-12)
    pf = ParticleFilter(model, Q=np.eye(2) * 1e-2, R=np.eye(2) * 0.1, num_particles=64)
    calls = counter(monkeypatch, ParticleFilter, "_step")
    key = jax.random.PRNGKey(0)
    assert_traced_once(
        calls,
        lambda: pf.run(key, x0, P0, ys, us),
        lambda: pf.run(jax.random.PRNGKey(1), x0 + 1.0, P0, ys + 1.0, us),
        lambda: pf.run(key, x0, P0, ys[:4], us[:4]),
    )
