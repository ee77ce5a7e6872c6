"""LQR against a dense KKT solve, iLQR (incl. box limits) against LQR and a dense QP, and
the bad-input contract."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose import Results
from jaxpose.control import (
    LQR,
    MPC,
    FunctionCost,
    QuadraticCost,
    box_qp,
    ilqr,
    lqr,
    lqr_solve,
)
from jaxpose.dynamics import LTI, LTV


# ----------------------------------------------------------------------------------
# Independent references (plain numpy)
# ----------------------------------------------------------------------------------
def dense_kkt(F, f, C, c, x0, CT, cT):
    """Solve the equality-constrained QP over z = [x_0..x_T, u_0..u_{T-1}] directly."""
    T, n, nm = F.shape
    m = nm - n
    nz = (T + 1) * n + T * m
    xi = lambda t: np.arange(t * n, (t + 1) * n)
    ui = lambda t: np.arange((T + 1) * n + t * m, (T + 1) * n + (t + 1) * m)
    H, g = np.zeros((nz, nz)), np.zeros(nz)
    for t in range(T):
        idx = np.r_[xi(t), ui(t)]
        H[np.ix_(idx, idx)] += C[t]
        g[idx] += c[t]
    H[np.ix_(xi(T), xi(T))] += CT
    g[xi(T)] += cT
    E, e = np.zeros(((T + 1) * n, nz)), np.zeros((T + 1) * n)
    E[:n, xi(0)] = np.eye(n)
    e[:n] = x0
    for t in range(T):
        r = slice((t + 1) * n, (t + 2) * n)
        E[r, xi(t + 1)] = np.eye(n)
        E[r, xi(t)] = -F[t][:, :n]
        E[r, ui(t)] = -F[t][:, n:]
        e[r] = f[t]
    K = np.block([[H, E.T], [E, np.zeros((E.shape[0], E.shape[0]))]])
    z = np.linalg.solve(K, np.r_[-g, e])
    return z[: (T + 1) * n].reshape(T + 1, n), z[(T + 1) * n : nz].reshape(T, m)


def random_problem(rng, T=6, n=4, m=2, time_varying=True):
    if time_varying:
        F = rng.normal(size=(T, n, n + m)) * 0.5
        F[:, :, :n] += np.eye(n)
    else:
        F = np.tile(
            np.c_[np.eye(n) + 0.2 * rng.normal(size=(n, n)), rng.normal(size=(n, m))], (T, 1, 1)
        )
    f = rng.normal(size=(T, n))
    M = rng.normal(size=(T, n + m, n + m))
    C = M @ M.transpose(0, 2, 1) + 0.1 * np.eye(n + m)
    c = rng.normal(size=(T, n + m))
    MT = rng.normal(size=(n, n))
    return F, f, C, c, rng.normal(size=n), MT @ MT.T, rng.normal(size=n)


LQR_SOLVE = jax.jit(lqr_solve)
N, M, T6 = 3, 2, 6
COST = QuadraticCost(
    np.eye(N + M), np.linspace(-1, 1, N + M), QT=2 * np.eye(N), pT=np.linspace(0.5, -0.5, N)
)
# One compiled iLQR (LTI, n=3, m=2, T=6) shared by several tests: compilation dominates.
ILQR = jax.jit(lambda A, B, c1, x: ilqr(LTI(A, B, c1=c1), COST, x, jnp.zeros((T6, M))))


@pytest.mark.parametrize("time_varying", [True, False])
def test_lqr_equals_dense_kkt(time_varying):
    rng = np.random.default_rng(1 + time_varying)
    F, f, C, c, x0, CT, cT = random_problem(rng, time_varying=time_varying)
    sol = LQR_SOLVE(F, f, C, c, x0, CT, cT)
    xs, us = dense_kkt(F, f, C, c, x0, CT, cT)
    np.testing.assert_allclose(sol.x, xs, atol=1e-9, rtol=0)
    np.testing.assert_allclose(sol.u, us, atol=1e-9, rtol=0)
    assert int(sol.status) == 0
    # the policy reproduces the controls and the reported cost is the cost of (x, u)
    np.testing.assert_allclose(
        np.einsum("tij,tj->ti", sol.K, sol.x[:-1]) + sol.k, sol.u, atol=1e-10
    )
    tau = np.c_[xs[:-1], us]
    J = 0.5 * np.einsum("ti,tij,tj->", tau, C, tau) + np.sum(c * tau)
    J += 0.5 * xs[-1] @ CT @ xs[-1] + cT @ xs[-1]
    np.testing.assert_allclose(sol.cost, J, rtol=1e-10)


def test_lqr_batched_vmap_matches_kkt():
    rng = np.random.default_rng(3)
    F, f, C, c, _, CT, cT = random_problem(rng, T=5, n=3, m=2)
    x0s = rng.normal(size=(6, 3))
    sols = jax.jit(jax.vmap(lambda x: lqr_solve(F, f, C, c, x, CT, cT)))(x0s)
    for i in range(6):
        xs, us = dense_kkt(F, f, C, c, x0s[i], CT, cT)
        np.testing.assert_allclose(sols.u[i], us, atol=1e-9, rtol=0)
    # batches of whole problems (different dynamics per element) vmap too
    Fb = np.stack([F, F * 0.9])
    solb = jax.jit(jax.vmap(lambda Fi, x: lqr_solve(Fi, f, C, c, x, CT, cT)))(Fb, x0s[:2])
    np.testing.assert_allclose(
        solb.u[1], dense_kkt(F * 0.9, f, C, c, x0s[1], CT, cT)[1], atol=1e-9, rtol=0
    )


def test_lqr_float32_path():
    rng = np.random.default_rng(4)
    F, f, C, c, x0, CT, cT = random_problem(rng, T=5, n=3, m=2)
    args = [a.astype(np.float32) for a in (F, f, C, c, x0, CT, cT)]
    sol = LQR_SOLVE(*args)
    assert sol.u.dtype == np.float32
    _, us = dense_kkt(F, f, C, c, x0, CT, cT)
    np.testing.assert_allclose(sol.u, us, rtol=2e-3, atol=2e-3)


def test_lqr_module_lti_ltv_and_ilqr_agree():
    rng = np.random.default_rng(5)
    n, m, T = N, M, T6
    A = np.eye(n) + 0.2 * rng.normal(size=(n, n))
    B = rng.normal(size=(n, m))
    c1 = rng.normal(size=n)
    x0 = rng.normal(size=(2, n))
    sol = eqx.filter_jit(LQR(LTI(A, B, c1=c1), COST, T))(x0)  # batched x0
    ltv = LTV(np.tile(A, (T, 1, 1)), np.tile(B, (T, 1, 1)), c1=np.tile(c1, (T, 1)))
    sol_v = eqx.filter_jit(lqr)(ltv, COST, x0[1], T)
    np.testing.assert_allclose(sol.u[1], sol_v.u, atol=1e-12)
    F = np.tile(np.c_[A, B], (T, 1, 1))
    C, c, CT, cT = COST.stacked(T, n)
    _, us = dense_kkt(
        F, np.tile(c1, (T, 1)), np.asarray(C), np.asarray(c), x0[1], np.asarray(CT), np.asarray(cT)
    )
    np.testing.assert_allclose(sol_v.u, us, atol=1e-9)
    it = ILQR(A, B, c1, x0[1])
    assert int(it.status) == 0 and int(it.iterations) <= 3
    np.testing.assert_allclose(it.u, us, atol=1e-9)


# ----------------------------------------------------------------------------------
# Box limits
# ----------------------------------------------------------------------------------
def brute_force_box_qp(H, g, lo, hi):
    """Enumerate active sets (each coordinate free / at lo / at hi); best feasible KKT point."""
    m = len(g)
    best, best_f = None, np.inf
    for code in np.ndindex(*(3,) * m):
        code = np.array(code)
        x = np.where(code == 1, lo, np.where(code == 2, hi, 0.0))
        fr = code == 0
        if fr.any():
            x[fr] = np.linalg.solve(H[np.ix_(fr, fr)], -(g[fr] + H[np.ix_(fr, ~fr)] @ x[~fr]))
        if np.all(x >= lo - 1e-12) and np.all(x <= hi + 1e-12):
            fx = 0.5 * x @ H @ x + g @ x
            if fx < best_f:
                best, best_f = x, fx
    return best


def test_box_qp_matches_enumeration():
    rng = np.random.default_rng(6)
    solve = jax.jit(box_qp)
    for _ in range(5):
        M = rng.normal(size=(3, 3))
        H = M @ M.T + 0.3 * np.eye(3)
        g = 3 * rng.normal(size=3)
        lo, hi = -np.abs(rng.normal(size=3)), np.abs(rng.normal(size=3))
        res = solve(H, g, lo, hi, np.zeros(3))
        np.testing.assert_allclose(res.x, brute_force_box_qp(H, g, lo, hi), atol=1e-9)
        assert np.all(res.x >= lo) and np.all(res.x <= hi) and bool(res.ok)


def condensed_box_reference(A, B, Q, p, x0, T, lo, hi, iters=20000):
    """The box-limited LQ problem as a QP in u alone, solved by projected gradient."""
    n, m = B.shape
    # x = Sx x0 + Su u (stacked x_0..x_T)
    Sx = np.vstack([np.linalg.matrix_power(A, t) for t in range(T + 1)])
    Su = np.zeros(((T + 1) * n, T * m))
    for t in range(1, T + 1):
        for s in range(t):
            Su[t * n : (t + 1) * n, s * m : (s + 1) * m] = np.linalg.matrix_power(A, t - 1 - s) @ B
    Qx, Qu, Qxu = Q[:n, :n], Q[n:, n:], Q[:n, n:]
    Hx = np.kron(np.diag(np.r_[np.ones(T), 0.0]), Qx)
    Hu = np.kron(np.eye(T), Qu)
    Hxu = np.zeros(((T + 1) * n, T * m))
    Hxu[: T * n] = np.kron(np.eye(T), Qxu)
    px = np.r_[np.tile(p[:n], T), np.zeros(n)]
    pu = np.tile(p[n:], T)
    H = Su.T @ Hx @ Su + Hu + Su.T @ Hxu + Hxu.T @ Su
    g = Su.T @ (Hx @ Sx @ x0 + px) + Hxu.T @ Sx @ x0 + pu
    u = np.zeros(T * m)
    step = 1.0 / np.linalg.eigvalsh(H).max()
    for _ in range(iters):
        u = np.clip(u - step * (H @ u + g), np.tile(lo, T), np.tile(hi, T))
    return u.reshape(T, m)


def test_ilqr_box_limits_equal_constrained_qp():
    rng = np.random.default_rng(7)
    n, m, T = 3, 2, 5
    A = np.eye(n) + 0.2 * rng.normal(size=(n, n))
    B = rng.normal(size=(n, m))
    Q, p = np.eye(n + m), 2 * rng.normal(size=n + m)
    x0 = 2 * rng.normal(size=n)
    lo, hi = np.array([-0.3, -0.5]), np.array([0.4, 0.2])
    sol = jax.jit(
        lambda x: ilqr(LTI(A, B), QuadraticCost(Q, p), x, jnp.zeros((T, m)), u_lower=lo, u_upper=hi)
    )(x0)
    assert int(sol.status) == 0
    assert np.all(sol.u >= lo) and np.all(sol.u <= hi)
    ref = condensed_box_reference(A, B, Q, p, x0, T, lo, hi)
    assert np.any(np.isclose(ref, lo) | np.isclose(ref, hi))  # limits are active
    np.testing.assert_allclose(sol.u, ref, atol=1e-6)


# ----------------------------------------------------------------------------------
# Bad input and status
# ----------------------------------------------------------------------------------
def test_lqr_bad_input():
    n, m, T = 3, 2, 4
    A, B = np.eye(n), np.ones((n, m))
    cost = QuadraticCost(np.eye(n + m))
    with pytest.raises(ValueError, match=r"Q: expected size n \+ m = 3 \+ 2"):
        LQR(LTI(A, B), QuadraticCost(np.eye(4)), T)
    with pytest.raises(ValueError, match="Q: expected a positive semi-definite"):
        QuadraticCost(np.diag([1.0, -1.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="QT: expected a positive semi-definite"):
        QuadraticCost(np.eye(5), QT=-np.eye(3))
    with pytest.raises(ValueError, match="p: expected last dimension 5"):
        QuadraticCost(np.eye(5), np.ones(4))
    with pytest.raises(ValueError, match="horizon: expected an int >= 1"):
        LQR(LTI(A, B), cost, -3)
    with pytest.raises(TypeError, match="horizon: expected an int >= 1"):
        LQR(LTI(A, B), cost, 2.5)
    with pytest.raises(ValueError, match=r"x0: expected shape \(\.\.\., 3\)"):
        lqr(LTI(A, B), cost, np.ones(4), T)
    with pytest.raises(ValueError, match="u_lower/u_upper: LQR has no control limits"):
        LQR(LTI(A, B), cost, T)(np.ones(n), u_lower=-1.0)
    with pytest.raises(ValueError, match=r"F: expected \(T, n, n\+m\)"):
        lqr_solve(np.ones((2, 3)), np.ones((2, 3)), np.ones((2, 5, 5)), np.ones((2, 5)), np.ones(3))
    with pytest.raises(ValueError, match=r"x0: expected shape \(3,\)"):
        lqr_solve(
            np.ones((2, 3, 5)), np.ones((2, 3)), np.ones((2, 5, 5)), np.ones((2, 5)), np.ones(2)
        )
    with pytest.raises(TypeError, match="system: LQR needs an LTI or LTV"):
        lqr(object(), cost, np.ones(n), T)
    with pytest.raises(ValueError, match="u_lower, u_upper: expected u_lower ≤ u_upper"):
        ilqr(LTI(A, B), cost, np.ones(n), np.zeros((T, m)), u_lower=1.0, u_upper=-1.0)
    with pytest.raises(ValueError, match=r"u_upper: expected a shape broadcastable to \(4, 2\)"):
        ilqr(LTI(A, B), cost, np.ones(n), np.zeros((T, m)), u_upper=np.ones(3))


def test_nonfinite_status_not_garbage():
    n, m, T = N, M, T6
    sol = eqx.filter_jit(lqr)(LTI(np.eye(n), np.ones((n, m))), COST, np.array([np.nan, 0, 0]), T)
    assert int(sol.status) == Results.NON_FINITE
    assert not np.all(np.isfinite(sol.u))  # reported, and the caller can see it
    # an indefinite problem reached under tracing (no eager check): Q_uu not PD
    bad = LQR_SOLVE(
        np.ones((T, 4, 6)),
        np.zeros((T, 4)),
        np.tile(-np.eye(6), (T, 1, 1)),
        np.zeros((T, 6)),
        np.ones(4),
        np.eye(4),
        np.zeros(4),
    )
    assert int(bad.status) == Results.NON_FINITE
    it = ILQR(np.eye(n), np.ones((n, m)), np.zeros(n), np.array([np.inf, 0.0, 0.0]))
    assert int(it.status) == Results.NON_FINITE


def test_issue19_overflow_status_nan_bounds_and_input_size():
    """Found by fault injection: x0 = 1e200 gave a finite trajectory, cost inf and status
    CONVERGED (now Results.NON_FINITE); NaN box bounds passed the u_lower ≤ u_upper check (NaN
    compares false) and only showed up as a Results.NON_FINITE status; a u_init of the wrong width
    raised an error naming the system's ``u``, not ``u_init``."""
    n, m, T = 3, 2, 4
    A, B = np.eye(n), np.ones((n, m))
    cost = QuadraticCost(np.eye(n + m))
    sol = lqr(LTI(A, B), cost, np.array([1e200, 0.0, 0.0]), T)
    assert not np.isfinite(float(sol.cost)) and int(sol.status) == Results.NON_FINITE
    with pytest.raises(ValueError, match="u_lower: contains NaN"):
        ilqr(LTI(A, B), cost, np.ones(n), np.zeros((T, m)), u_lower=np.array([np.nan, 0.0]))
    with pytest.raises(ValueError, match=r"x0, u_init: .*u_init\[t\] \(3,\)"):
        ilqr(LTI(A, B), cost, np.ones(n), np.zeros((T, 3)))


# ----------------------------------------------------------------------------------
# Time-varying terms shorter than the horizon; shape errors naming the argument
# ----------------------------------------------------------------------------------
A2, B2, X2 = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]]), np.array([1.0, 0.5])


def test_ilqr_time_varying_cost_or_ltv_shorter_than_horizon_raises():
    """JAX gathers clamp ``Q[t]``/``A[t]``: iLQR (and MPC's iLQR path) silently reused the
    last step of a time-varying cost or LTV system shorter than the horizon, where lqr
    raised. A start step t0 must keep the horizon inside the steps (eagerly, or by
    ``eqx.error_if`` under jit); a negative step no longer wraps around."""
    T = 6
    q_tv = np.stack([np.diag([1.0, 1.0, w]) for w in (0.1, 0.2, 0.3)])
    with pytest.raises(ValueError, match="horizon: 6 exceeds the cost's 3 time steps"):
        ilqr(LTI(A2, B2), QuadraticCost(q_tv, QT=np.eye(2)), X2, np.zeros((T, 1)))
    ltv = LTV(np.stack([A2 * s for s in (1.0, 1.1, 1.2)]), np.stack([B2] * 3))
    with pytest.raises(ValueError, match="horizon: 6 exceeds the LTV system's 3 time steps"):
        ilqr(ltv, QuadraticCost(np.eye(3), QT=np.eye(2)), X2, np.zeros((T, 1)))
    fcost = FunctionCost(lambda x, u, t: x @ x + u @ u)
    with pytest.raises(ValueError, match="horizon: 6 exceeds the LTV system's 3 time steps"):
        ilqr(ltv, fcost, X2, np.zeros((T, 1)))
    with pytest.raises(ValueError, match="horizon: 6 exceeds the LTV system's 3 time steps"):
        MPC(ltv, fcost, T)
    q4 = QuadraticCost(np.tile(np.eye(3), (4, 1, 1)))
    for t0, message in ((2, "t0: expected 0 ≤ t0 ≤ 1"), (-1, "t0: expected a time step >= 0")):
        with pytest.raises(ValueError, match=message):
            ilqr(LTI(A2, B2), q4, X2, np.zeros((3, 1)), t0=t0)
    with pytest.raises(RuntimeError, match="t0: expected 0 ≤ t0 ≤ 1"):
        jax.block_until_ready(jax.jit(lambda t0: ilqr(LTI(A2, B2), q4, X2, np.zeros((3, 1)),
                                                      t0=t0).u)(2))
    with pytest.raises(ValueError, match="t: expected a time step index >= 0"):
        QuadraticCost(q_tv).stage(np.zeros(2), np.zeros(1), -1)


def test_ilqr_time_varying_cost_from_t0_equals_dense_kkt():
    """The last allowed start (t0 = steps − T) uses Q[t0 : t0 + T] (dense KKT in numpy)."""
    rng = np.random.default_rng(7)
    T, t0 = 4, 2
    M = rng.normal(size=(T + t0, 3, 3))
    Q = M @ M.transpose(0, 2, 1) + 0.5 * np.eye(3)
    sol = ilqr(LTI(A2, B2), QuadraticCost(Q, QT=np.eye(2)), X2, np.zeros((T, 1)), t0=t0)
    F = np.tile(np.c_[A2, B2], (T, 1, 1))
    xs, us = dense_kkt(F, np.zeros((T, 2)), Q[t0:], np.zeros((T, 3)), X2, np.eye(2), np.zeros(2))
    assert int(sol.status) == Results.CONVERGED
    np.testing.assert_allclose(sol.u, us, atol=1e-9)
    np.testing.assert_allclose(sol.x, xs, atol=1e-9)


def test_ilqr_and_mpc_shape_errors_name_the_argument():
    """A QT or Q of the wrong size reached iLQR's dot products (raw TypeError); limits of
    shape (3,) with m = 1 passed the broadcast check ((3,) with (T, 1) gives (T, 3))."""
    T, cost = 6, QuadraticCost(np.eye(3))
    with pytest.raises(ValueError, match=r"QT: expected shape \(2, 2\)"):
        ilqr(LTI(A2, B2), QuadraticCost(np.eye(3), QT=np.eye(3)), X2, np.zeros((T, 1)))
    with pytest.raises(ValueError, match=r"Q: expected size n \+ m = 2 \+ 1 = 3"):
        ilqr(LTI(A2, B2), QuadraticCost(np.eye(4)), X2, np.zeros((T, 1)))
    with pytest.raises(ValueError, match=r"u_lower: expected a shape broadcastable to \(6, 1\)"):
        ilqr(LTI(A2, B2), cost, X2, np.zeros((T, 1)), u_lower=np.zeros(3))
    with pytest.raises(ValueError, match=r"u_upper: expected a shape broadcastable to \(6, 1\)"):
        MPC(LTI(A2, B2), cost, T, u_upper=np.ones(3))(X2)
    with pytest.raises(ValueError, match=r"u_lower: expected a shape broadcastable to \(6, 1\)"):
        ilqr(LTI(A2, B2), cost, X2, np.zeros((T, 1)), u_lower=np.zeros((1, 6, 1)))


# ----------------------------------------------------------------------------------
# Found by an audit (session 48): inputs that gave a "converged" wrong answer
# ----------------------------------------------------------------------------------
def test_box_iters_below_one_are_refused():
    """Zero projected-Newton iterations returned the clipped warm start (u = 0), which
    iLQR then reported CONVERGED at a cost above the box-constrained optimum."""
    A, B = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]])
    cost = QuadraticCost(np.diag([1.0, 0.1, 0.01]), None, np.eye(2))
    for bad, error in ((0, ValueError), (-3, ValueError), (2.0, TypeError), (True, TypeError)):
        with pytest.raises(error, match="box_iters: expected an int >= 1"):
            ilqr(LTI(A, B), cost, np.array([3.0, 0.5]), np.zeros((5, 1)), u_lower=-1.0,
                 u_upper=1.0, box_iters=bad)
        with pytest.raises(error, match="box_iters: expected an int >= 1"):
            MPC(LTI(A, B), cost, 5, u_lower=-1.0, u_upper=1.0, box_iters=bad)
    with pytest.raises(ValueError, match="iters: expected an int >= 1"):
        box_qp(np.eye(2), np.ones(2), -np.ones(2), np.ones(2), np.zeros(2), iters=0)
    one = ilqr(LTI(A, B), cost, np.array([3.0, 0.5]), np.zeros((5, 1)), u_lower=-1.0,
               u_upper=1.0, box_iters=1)
    np.testing.assert_allclose(one.u[:, 0], [-1, -1, -1, -1, -0.5], atol=1e-9)  # enumeration


def test_crossed_or_nan_limits_raise_under_jit():
    """Traced limits (MPC's are differentiable fields) skipped the eager lo ≤ hi check:
    under jit every control was clamped to u_upper with status CONVERGED."""
    A, B = np.eye(2), np.ones((2, 1))
    cost = QuadraticCost(np.eye(3))

    @jax.jit
    def mpc_u(lo, hi):
        return MPC(LTI(A, B), cost, 4, u_lower=lo, u_upper=hi)(jnp.ones(2)).u

    @jax.jit
    def ilqr_u(lo, hi):
        return ilqr(LTI(A, B), cost, jnp.ones(2), jnp.zeros((4, 1)), u_lower=lo, u_upper=hi).u

    for solve in (mpc_u, ilqr_u):
        with pytest.raises(RuntimeError, match="u_lower, u_upper: expected u_lower ≤ u_upper"):
            jax.block_until_ready(solve(1.0, -1.0))
        with pytest.raises(RuntimeError, match="u_lower: contains NaN"):
            jax.block_until_ready(solve(jnp.nan, 1.0))
        assert np.all(np.abs(solve(-0.1, 0.1)) <= 0.1 + 1e-12)  # a valid box still solves
    with pytest.raises(ValueError, match="lo, hi: expected lo ≤ hi"):
        box_qp(np.eye(2), np.ones(2), np.ones(2), -np.ones(2), np.zeros(2))
    with pytest.raises(RuntimeError, match="lo, hi: expected lo ≤ hi"):
        jax.block_until_ready(jax.jit(box_qp)(np.eye(2), np.ones(2), np.ones(2), -np.ones(2),
                                              np.zeros(2)))
    with pytest.raises(ValueError, match=r"hi: expected shape \(2,\) like g"):
        box_qp(np.eye(2), np.ones(2), -np.ones(2), np.ones(3), np.zeros(2))
    with pytest.raises(ValueError, match=r"H, g: expected shapes \(m, m\) and \(m,\)"):
        box_qp(np.eye(3), np.ones(2), -np.ones(2), np.ones(2), np.zeros(2))


def test_tracking_cost_with_a_nonsymmetric_weight():
    """Only Q's symmetric part enters the stage cost, so the linear term must be
    −sym(Q)·τ_ref: with −Q·τ_ref the minimum was not at τ_ref."""
    Q = np.array([[2.0, 1.0, 0.0], [0.0, 2.0, 0.5], [0.0, 0.0, 1.0]])  # n = 2, m = 1
    QT = np.array([[2.0, 1.0], [0.0, 2.0]])
    ref, x_ref = np.array([1.0, -1.0, 0.5]), np.array([0.2, 0.3])
    cost = QuadraticCost.tracking(Q, ref, QT=QT, x_ref=x_ref)
    tau = np.array([0.3, 0.7, -0.4])
    by_hand = 0.5 * (tau - ref) @ Q @ (tau - ref) - 0.5 * ref @ Q @ ref
    np.testing.assert_allclose(cost.stage(tau[:2], tau[2:], 0), by_hand, rtol=1e-12)
    x = tau[:2]
    by_hand = 0.5 * (x - x_ref) @ QT @ (x - x_ref) - 0.5 * x_ref @ QT @ x_ref
    np.testing.assert_allclose(cost.terminal(x), by_hand, rtol=1e-12)
    grad = jax.grad(lambda t: cost.stage(t[:2], t[2:], 0))(jnp.asarray(ref))
    np.testing.assert_allclose(grad, 0.0, atol=1e-12)


def test_riccati_returns_what_it_documents_and_lqr_solve_checks_free():
    from jaxpose.control import lq_problem, riccati

    A, B = np.eye(2), np.ones((2, 1))
    F, f, C, c, CT, cT = lq_problem(LTI(A, B), QuadraticCost(np.eye(3), None, np.eye(2)), 3)
    K, k, V, v, ok, L = riccati(F, f, C, c, CT, cT)
    assert K.shape == (3, 1, 2) and V.shape == (4, 2, 2) and L.shape == (3, 1, 1) and bool(ok)
    Quu = C[-1, 2:, 2:] + F[-1, :, 2:].T @ CT @ F[-1, :, 2:]  # last step, by hand
    np.testing.assert_allclose(L[-1] @ L[-1].T, Quu, rtol=1e-12)
    for bad in (np.ones(3, bool), np.ones((3, 2), bool), np.ones((3, 1))):
        with pytest.raises(ValueError, match=r"free: expected a \(3, 1\) \(T, m\) bool mask"):
            lqr_solve(F, f, C, c, np.ones(2), CT, cT, free=bad)
    held = lqr_solve(F, f, C, c, np.ones(2), CT, cT, free=np.array([[True], [False], [True]]))
    assert float(held.u[1, 0]) == 0.0
