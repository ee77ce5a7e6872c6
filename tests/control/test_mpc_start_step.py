"""MPC at a start step t0 and closed_loop's advancing time.

Before t0 existed, every MPC solve read an LTV system, a time-varying cost or a
time-dependent cost at steps 0 … T−1, so closed_loop silently re-solved the problem of
step 0 at every step while its plant advanced. The reference throughout is the same
problem cut by hand (NumPy slices of the per-step arrays, or a cost function shifted by
t0) and solved from step 0."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose import Results
from jaxpose.control import LQR, MPC, FunctionCost, QuadraticCost, closed_loop, lqr
from jaxpose.dynamics import LTV

jax.config.update("jax_enable_x64", True)

K, T, N, M = 9, 4, 2, 1  # steps of the time-varying parts, horizon, states, inputs


def _problem(seed=0):
    rng = np.random.default_rng(seed)
    A = np.stack([np.array([[1.0, 0.1], [0.0, 1.0]]) + 0.05 * rng.normal(size=(N, N))
                  for _ in range(K)])
    B = np.stack([np.array([[0.0], [0.1]]) * (1.0 + 0.3 * k) for k in range(K)])
    Q = np.stack([np.diag([1.0 + 0.2 * k, 0.1, 0.01 * (1 + k)]) for k in range(K)])
    p = 0.1 * rng.normal(size=(K, N + M))
    return A, B, Q, p


def _mpc(A, B, Q, p, **kw):
    return MPC(LTV(A, B), QuadraticCost(Q, p, QT=5.0 * np.eye(N)), T, **kw)


@pytest.mark.parametrize("limits", [None, 0.4], ids=["lqr", "ilqr-with-limits"])
@pytest.mark.parametrize("t0", [0, 3, K - T])
def test_mpc_at_t0_solves_the_steps_t0_on(limits, t0):
    A, B, Q, p = _problem()
    kw = {} if limits is None else {"u_lower": -limits, "u_upper": limits}
    x0 = np.array([1.0, -0.5])
    got = _mpc(A, B, Q, p, **kw)(x0, t0=t0)
    cut = slice(t0, t0 + T)
    ref = _mpc(A[cut], B[cut], Q[cut], p[cut], **kw)(x0)
    assert int(got.status) == Results.CONVERGED == int(ref.status)
    np.testing.assert_allclose(got.u, ref.u, atol=1e-10)
    np.testing.assert_allclose(got.x, ref.x, atol=1e-10)
    np.testing.assert_allclose(got.cost, ref.cost, rtol=1e-12)
    if 0 < t0:  # the steps matter: solving from step 0 is another problem
        assert np.max(np.abs(_mpc(A, B, Q, p, **kw)(x0).u - ref.u)) > 1e-3


def test_lqr_at_t0_solves_the_steps_t0_on():
    A, B, Q, p = _problem()
    cost = lambda q, pp: QuadraticCost(q, pp, QT=5.0 * np.eye(N))  # noqa: E731
    x0, cut = np.array([[1.0, -0.5], [0.2, 0.3]]), slice(3, 3 + T)
    ref = lqr(LTV(A[cut], B[cut]), cost(Q[cut], p[cut]), x0, T)
    for got in (lqr(LTV(A, B), cost(Q, p), x0, T, t0=3),
                LQR(LTV(A, B), cost(Q, p), T)(x0, t0=jnp.int32(3))):
        np.testing.assert_allclose(got.u, ref.u, atol=1e-12)
        np.testing.assert_allclose(got.x, ref.x, atol=1e-12)
    with pytest.raises(ValueError, match=rf"t0: expected 0 ≤ t0 ≤ {K - T}"):
        lqr(LTV(A, B), cost(Q, p), x0, T, t0=K - T + 1)


def test_traced_t0_matches_and_does_not_recompile():
    A, B, Q, p = _problem()
    mpc, x0 = _mpc(A, B, Q, p), np.array([1.0, -0.5])
    solve = eqx.filter_jit(lambda m, t: m(x0, t0=t).u)
    for t0 in (1, 5):
        np.testing.assert_allclose(solve(mpc, jnp.int32(t0)), mpc(x0, t0=t0).u, atol=1e-12)
    assert solve._cached._cache_size() == 1


def test_time_dependent_function_cost_reads_t0_on():
    # the iLQR path with a general cost: ℓ(x, u, t) reads t, the reference shifts it
    A, B, _, _ = _problem()
    lti_like = LTV(np.repeat(A[:1], K, 0), np.repeat(B[:1], K, 0))

    def stage(shift):
        return lambda x, u, t: (1.0 + jnp.sin(t + shift)) * (x @ x) + 0.1 * u @ u

    x0 = np.array([1.0, -0.5])
    got = MPC(lti_like, FunctionCost(stage(0.0)), T, solver="ilqr")(x0, t0=3)
    ref = MPC(lti_like, FunctionCost(stage(3.0)), T, solver="ilqr")(x0)
    np.testing.assert_allclose(got.u, ref.u, atol=1e-9)
    np.testing.assert_allclose(got.cost, ref.cost, rtol=1e-10)


@pytest.mark.parametrize("gradient", ["implicit", "unroll"])
def test_derivative_at_t0_matches_the_cut_problem_and_finite_differences(gradient):
    A, B, Q, p = _problem()
    x0, t0, cut = np.array([1.0, -0.5]), 2, slice(2, 2 + T)
    limits = {"u_lower": -0.4, "u_upper": 0.4}

    def loss(scale, start, whole):
        a = A * scale if whole else A[cut] * scale
        b, q, pp = (B, Q, p) if whole else (B[cut], Q[cut], p[cut])
        mpc = MPC(LTV(a, b), QuadraticCost(q, pp, QT=5.0 * np.eye(N)), T, max_iter=100,
                  gradient=gradient, **limits)
        sol = mpc(x0, t0=start)
        return jnp.sum(sol.u ** 2) + sol.cost

    g = jax.grad(lambda s: loss(s, t0, True))(1.0)
    g_ref = jax.grad(lambda s: loss(s, 0, False))(1.0)
    eps = 1e-6
    fd = (loss(1.0 + eps, t0, True) - loss(1.0 - eps, t0, True)) / (2 * eps)
    np.testing.assert_allclose(g, g_ref, rtol=1e-9)
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_bad_t0_raises_naming_it():
    A, B, Q, p = _problem()
    mpc, x0 = _mpc(A, B, Q, p), np.array([1.0, -0.5])
    with pytest.raises(ValueError, match=rf"t0: expected 0 ≤ t0 ≤ {K - T}"):
        mpc(x0, t0=K - T + 1)
    with pytest.raises(ValueError, match="t0: expected a time step >= 0"):
        mpc(x0, t0=-1)
    with pytest.raises(ValueError, match="t0: expected an integer time step"):
        mpc(x0, t0=1.5)
    with pytest.raises(ValueError, match="t0: expected a scalar time step"):
        mpc(x0, t0=np.array([1, 2]))
    with pytest.raises(RuntimeError, match=rf"t0: expected 0 ≤ t0 ≤ {K - T}"):
        jax.block_until_ready(eqx.filter_jit(lambda t: mpc(x0, t0=t).u)(jnp.int32(K)))
    with pytest.raises(ValueError, match=rf"t0: expected 0 ≤ t0 ≤ {K - T}"):
        LTV(A, B).matrices(T, K - T + 1)
    with pytest.raises(ValueError, match=rf"t0: expected 0 ≤ t0 ≤ {K - T}"):
        QuadraticCost(Q, p).stacked(T, N, K - T + 1)


def test_closed_loop_advances_the_mpc_problem_with_the_plant():
    A, B, Q, p = _problem()
    mpc, plant = _mpc(A, B, Q, p), LTV(A, B)
    x0, steps = np.array([1.0, -0.5]), K - T + 1
    xs, us, status = closed_loop(mpc, plant, x0, steps)
    assert np.all(status == Results.CONVERGED)
    # reference: at step t, the MPC of the steps t … t+T−1 cut by hand, warm-started
    x, warm, ref_u = x0, np.zeros((T, M)), []
    for t in range(steps):
        cut = slice(t, t + T)
        sol = _mpc(A[cut], B[cut], Q[cut], p[cut])(x, warm)
        u0 = np.asarray(sol.u[0])
        ref_u.append(u0)
        warm = np.concatenate([sol.u[1:], sol.u[-1:]], 0)
        x = A[t] @ x + B[t] @ u0
    np.testing.assert_allclose(us, np.stack(ref_u), atol=1e-10)
    np.testing.assert_allclose(xs[-1], x, atol=1e-10)
    with pytest.raises(ValueError, match=rf"steps: expected at most {K - T + 1}"):
        closed_loop(mpc, plant, x0, steps + 1)
