"""MPC: gradients (implicit and unrolled) against central finite differences, receding
horizon, cart-pole iLQR with force limits, and bad input."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from jaxpose import Results
from jaxpose.control import (
    MPC,
    QuadraticCost,
    closed_loop,
)
from jaxpose.dynamics import LTI, Pendulum


def fd_grad(f, flat, eps=1e-6):
    """Central differences of a scalar function of a flat vector: one jitted forward,
    called 2·size times (cheaper than compiling a vmapped one)."""
    fj = jax.jit(f)
    E = np.eye(flat.size) * eps
    return np.array([(fj(flat + e) - fj(flat - e)) / (2 * eps) for e in E])


# ----------------------------------------------------------------------------------
# Linear–quadratic: every differentiable input, batched x0
# ----------------------------------------------------------------------------------
def lq_setup(dtype=np.float64):
    rng = np.random.default_rng(11)
    n, m, T = 3, 2, 5
    params = (
        np.eye(n) + 0.2 * rng.normal(size=(n, n)),  # A
        rng.normal(size=(n, m)),  # B
        np.eye(n + m) + 0.1 * np.ones((n + m, n + m)),  # Q
        rng.normal(size=n + m),  # p
        rng.normal(size=(2, n)),  # x0 (batch of 2)
    )
    flat, unravel = ravel_pytree(tuple(jnp.asarray(a, dtype) for a in params))
    wx = jnp.asarray(rng.normal(size=(2, T + 1, n)), dtype)
    wu = jnp.asarray(rng.normal(size=(2, T, m)), dtype)

    def make(gradient):
        def loss(flat):
            A, B, Q, p, x0 = unravel(flat)
            sol = MPC(
                LTI(A, B), QuadraticCost(Q, p, QT=jnp.eye(n, dtype=dtype)), T, gradient=gradient
            )(x0)
            return jnp.sum(wx * sol.x) + jnp.sum(wu * sol.u) + 0.1 * jnp.sum(sol.cost)

        return loss

    return flat, make


def test_lq_mpc_gradients_implicit_and_unrolled_match_fd_and_float32():
    flat, make = lq_setup()
    g_imp = jax.jit(jax.grad(make("implicit")))(flat)
    g_unr = jax.jit(jax.grad(make("unroll")))(flat)
    fd = fd_grad(make("implicit"), flat)
    np.testing.assert_allclose(g_imp, fd, atol=1e-7, rtol=1e-6)
    np.testing.assert_allclose(g_unr, fd, atol=1e-7, rtol=1e-6)
    np.testing.assert_allclose(g_imp, g_unr, atol=1e-10, rtol=1e-9)
    flat32, make32 = lq_setup(np.float32)
    g32 = jax.jit(jax.grad(make32("implicit")))(flat32)
    assert g32.dtype == np.float32
    np.testing.assert_allclose(g32, g_imp, rtol=2e-3, atol=2e-3 * float(jnp.abs(g_imp).max()))


# ----------------------------------------------------------------------------------
# Nonlinear dynamics with active control limits (iLQR path)
# ----------------------------------------------------------------------------------
def pendulum_setup():
    T = 6
    goal = jnp.array([1.0, 0.0, 0.0])  # [θ, ω, u] reference
    params = (
        jnp.array([1.0, 0.3]),  # pendulum length, damping
        jnp.array([2.0, 0.2, 0.5]),  # cost weights diag(Q)
        jnp.array([0.2, -0.5]),  # x0
    )
    flat, unravel = ravel_pytree(params)
    rng = np.random.default_rng(12)
    wx, wu = jnp.asarray(rng.normal(size=(T + 1, 2))), jnp.asarray(rng.normal(size=(T, 1)))

    def make(gradient, u_max=0.5):
        def loss(flat):
            (length, damping), q, x0 = unravel(flat)
            model = Pendulum(dt=0.1, length=length, damping=damping)
            cost = QuadraticCost.tracking(jnp.diag(q), goal, QT=5 * jnp.eye(2), x_ref=goal[:2])
            mpc = MPC(
                model,
                cost,
                T,
                u_lower=-u_max,
                u_upper=u_max,
                gradient=gradient,
                max_iter=40,
                tol=1e-15,
            )
            sol = mpc(x0, jnp.zeros((T, 1)))
            return jnp.sum(wx * sol.x) + jnp.sum(wu * sol.u), sol

        return loss

    return flat, make


def test_nonlinear_mpc_with_limits_implicit_gradient_matches_fd():
    flat, make = pendulum_setup()
    loss = make("implicit")
    (val, sol), g = jax.jit(jax.value_and_grad(loss, has_aux=True))(flat)
    assert int(sol.status) == Results.CONVERGED
    clamped = np.abs(sol.u) >= 0.5 - 1e-12
    assert np.any(clamped) and not np.all(clamped), "a mix of active and free limits"
    assert np.all(np.abs(sol.u) <= 0.5)
    fd = fd_grad(lambda f: loss(f)[0], flat)
    np.testing.assert_allclose(g, fd, atol=1e-6, rtol=1e-5)


@pytest.mark.slow
def test_nonlinear_mpc_with_limits_unrolled_gradient_matches_fd():
    flat, make = pendulum_setup()
    (val, sol), g = jax.jit(jax.value_and_grad(make("unroll"), has_aux=True))(flat)
    fd = fd_grad(lambda f: make("implicit")(f)[0], flat)
    np.testing.assert_allclose(g, fd, atol=1e-6, rtol=1e-5)


# ----------------------------------------------------------------------------------
# Receding horizon
# ----------------------------------------------------------------------------------
def test_closed_loop_regulates_lti():
    rng = np.random.default_rng(13)
    A = np.array([[1.0, 0.1], [0.0, 1.0]])
    B = np.array([[0.0], [0.1]])
    plant = LTI(A, B)
    mpc = MPC(plant, QuadraticCost(np.diag([1.0, 0.1, 0.01]), QT=10 * np.eye(2)), 10)
    xs, us, status = eqx.filter_jit(closed_loop)(mpc, plant, rng.normal(size=2), 40)
    assert xs.shape == (41, 2) and us.shape == (40, 1) and np.all(status == Results.CONVERGED)
    assert np.linalg.norm(xs[-1]) < 0.05 * np.linalg.norm(xs[0])


# ----------------------------------------------------------------------------------
# Cart-pole with force limits
# ----------------------------------------------------------------------------------
CP_UMAX = 5.0


def _cartpole(x0, u_max, max_iter):
    """The notebook's solver (horizon 80, dt 0.05): one compilation for all these tests
    and the example's smoke test."""
    from notebooks._examples.cartpole_ilqr import solve

    return solve(u_max=u_max, max_iter=max_iter, x0=x0)[0]


def test_cartpole_balance_converges_within_limits():
    sol = _cartpole(jnp.array([0.0, 0.0, 0.6, 0.0]), 2.0, 400)
    assert int(sol.status) == Results.CONVERGED
    assert np.all(np.abs(sol.u) <= 2.0) and np.any(np.abs(sol.u) >= 2.0 - 1e-12)
    assert np.cos(float(sol.x[-1, 2])) > 0.999 and abs(float(sol.x[-1, 0])) < 0.05


@pytest.mark.slow
def test_cartpole_swing_up_converges_within_limits():
    sol = _cartpole(jnp.array([0.0, 0.0, np.pi, 0.0]), CP_UMAX, 400)
    assert int(sol.status) == Results.CONVERGED
    assert np.all(np.abs(sol.u) <= CP_UMAX)
    assert np.sum(np.abs(sol.u) >= CP_UMAX - 1e-12) >= 5  # the limit binds
    assert np.cos(float(sol.x[-1, 2])) > 0.999  # upright
    assert abs(float(sol.x[-1, 0])) < 0.05 and abs(float(sol.x[-1, 3])) < 0.05


def test_ilqr_max_iter_status_and_limits_on_early_stop():
    sol = _cartpole(jnp.array([0.0, 0.0, np.pi, 0.0]), 1.0, 3)
    assert int(sol.status) == Results.MAX_STEPS and int(sol.iterations) == 3
    assert np.all(np.abs(sol.u) <= 1.0)


# ----------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------
def test_mpc_bad_input():
    A, B = np.eye(2), np.ones((2, 1))
    cost = QuadraticCost(np.eye(3))
    with pytest.raises(ValueError, match=r"x0: expected last dimension 2"):
        MPC(LTI(A, B), cost, 4)(np.ones(3))
    with pytest.raises(ValueError, match=r"u_init: expected shape \(\.\.\., 4, 1\)"):
        MPC(LTI(A, B), cost, 4, solver="ilqr")(np.ones(2), np.zeros((3, 1)))
    with pytest.raises(ValueError, match="horizon: expected an int >= 1"):
        MPC(LTI(A, B), cost, 0)
    with pytest.raises(ValueError, match="gradient: expected one of"):
        MPC(LTI(A, B), cost, 4, gradient="fd")
    with pytest.raises(ValueError, match="solver: 'lqr' needs"):
        MPC(Pendulum(), cost, 4, solver="lqr")(np.ones(2), np.zeros((4, 1)))
    with pytest.raises(ValueError, match=r"Q: expected size n \+ m = 2 \+ 1"):
        MPC(LTI(A, B), QuadraticCost(np.eye(4)), 4)
    with pytest.raises(ValueError, match="u_lower, u_upper: expected u_lower ≤ u_upper"):
        MPC(LTI(A, B), cost, 4, u_lower=1.0, u_upper=0.0)(np.ones(2))
    sol = eqx.filter_jit(MPC(LTI(A, B), cost, 4))(np.array([np.nan, 1.0]))
    assert int(sol.status) == Results.NON_FINITE


def _limited_effort(a01, gradient):
    """Issue 16's case: Σu² of a 10-step MPC with limits ±0.5 as a function of A[0, 1]."""
    A = jnp.array([[1.0, a01], [0.0, 1.0]])
    B = jnp.array([[0.0], [0.1]])
    mpc = MPC(LTI(A, B), QuadraticCost(jnp.eye(3)), 10, u_lower=-0.5, u_upper=0.5,
              gradient=gradient)
    return jnp.sum(mpc(jnp.array([1.0, 0.0])).u ** 2)


def _second_difference(f, a, h=1e-3):
    """Richardson-extrapolated second central difference of a scalar function."""
    d = lambda h: (f(a + h) - 2 * f(a) + f(a - h)) / h**2  # noqa: E731
    return (4 * d(h / 2) - d(h)) / 3


@pytest.mark.parametrize("limits", [True, False], ids=["limits", "no_limits"])
def test_second_derivative_through_implicit_mpc_matches_finite_differences(limits):
    """Issue 16's case (d²(Σu²)/dA[0,1]² through MPC with limits ±0.5, and without):
    the former backward pass held the trajectory fixed and missed most of the second
    derivative. The custom_jvp rule is exact at every order."""

    def effort(a01):
        A = jnp.array([[1.0, a01], [0.0, 1.0]])
        B = jnp.array([[0.0], [0.1]])
        lim = dict(u_lower=-0.5, u_upper=0.5) if limits else {}
        mpc = MPC(LTI(A, B), QuadraticCost(jnp.eye(3)), 10, **lim)
        return jnp.sum(mpc(jnp.array([1.0, 0.0])).u ** 2)

    f = jax.jit(effort)
    d2 = float(jax.jit(jax.jacfwd(jax.jacrev(effort)))(0.1))
    assert d2 == pytest.approx(float(jax.jit(jax.hessian(effort))(0.1)), rel=1e-12)
    assert d2 == pytest.approx(float(jax.jit(jax.grad(jax.grad(effort)))(0.1)), rel=1e-12)
    fd = float(_second_difference(f, 0.1))
    assert d2 == pytest.approx(fd, rel=1e-5)
    d1 = float(jax.jit(jax.jacfwd(effort))(0.1))
    assert d1 == pytest.approx(float(jax.jit(jax.grad(effort))(0.1)), rel=1e-12)


def test_implicit_mpc_derivative_wrt_active_control_limits():
    """An active limit moves its clamped controls (and through them the free ones):
    d(Σu)/d(u_upper) and the second derivative against central differences."""

    def total(hi):
        mpc = MPC(LTI(jnp.array([[1.0, 0.1], [0.0, 1.0]]), jnp.array([[0.0], [0.1]])),
                  QuadraticCost(jnp.eye(3)), 10, u_lower=-0.5, u_upper=hi)
        return jnp.sum(mpc(jnp.array([-5.0, 0.0])).u)  # the first 4 controls at u_upper

    f = jax.jit(total)
    g = float(jax.jit(jax.grad(total))(0.5))
    fd = float((f(0.5 + 1e-5) - f(0.5 - 1e-5)) / 2e-5)
    assert g == pytest.approx(fd, rel=1e-6, abs=1e-8)
    assert abs(g) > 0.5  # at least one control is at the limit
    assert float(jax.jit(jax.hessian(total))(0.5)) == pytest.approx(
        float(_second_difference(f, 0.5, 1e-3)), rel=1e-4, abs=1e-6)


@pytest.mark.slow  # an eager Hessian through 10 unrolled box-QP solves (minutes of tracing)
def test_second_derivative_through_unrolled_mpc_matches_finite_differences():
    """The unrolled gradient gives the second derivative of the issue-16 case too
    (-79.98 by finite differences)."""
    effort = _limited_effort
    d2 = float(jax.jacfwd(jax.jacrev(effort))(0.1, "unroll"))
    f = jax.jit(lambda a: effort(a, "unroll"))
    h = 1e-3
    fd = float((f(0.1 + h) - 2 * f(0.1) + f(0.1 - h)) / h**2)
    assert d2 == pytest.approx(fd, rel=1e-3, abs=1e-6)


def test_implicit_gradient_of_an_unconverged_solve_raises():
    """Two iLQR iterations leave the pendulum's MPC short of its optimum (status
    max_steps): the implicit function theorem does not hold there, so the implicit
    gradient raises; the unrolled one (of the iterates taken) stays available."""
    def effort(length, gradient):
        mpc = MPC(Pendulum(dt=0.1, length=length), QuadraticCost.tracking(
            jnp.eye(3), jnp.array([1.0, 0.0, 0.0])), 6, gradient=gradient, max_iter=2)
        sol = mpc(jnp.array([0.2, -0.5]), jnp.zeros((6, 1)))
        return jnp.sum(sol.u ** 2), sol.status

    _, status = effort(1.0, "implicit")
    assert int(status) == Results.MAX_STEPS
    match = r"MPC\(gradient='implicit'\): cannot differentiate the solution: the solver stopped"
    with pytest.raises(Exception, match=match):
        jax.block_until_ready(jax.grad(lambda a: effort(a, "implicit")[0])(1.0))
    assert np.isfinite(float(jax.grad(lambda a: effort(a, "unroll")[0])(1.0)))


def test_an_unconverged_problem_masked_out_of_a_batch_does_not_block_its_gradient():
    """A batch of two starts, two iLQR iterations: from rest at the target the solve
    converges, from x0 = (0.2, −0.5) it stops (max_steps). A loss that masks the second
    out has the first's own gradient; it raised for the whole batch."""
    x0s = jnp.array([[0.0, 0.0], [0.2, -0.5]])

    def effort(length, x0):
        mpc = MPC(Pendulum(dt=0.1, length=length), QuadraticCost.tracking(
            jnp.eye(3), jnp.array([1.0, 0.0, 0.0])), 6, gradient="implicit", max_iter=2)
        sol = mpc(x0, jnp.zeros((6, 1)))
        return jnp.sum(sol.u ** 2), sol.status

    def masked(length):
        e, status = jax.vmap(lambda x0: effort(length, x0))(x0s)
        return jnp.sum(jnp.where(status == Results.CONVERGED, e, 0.0))

    status = jax.vmap(lambda x0: effort(1.0, x0))(x0s)[1]
    assert status.tolist() == [Results.CONVERGED, Results.MAX_STEPS]
    alone = jax.grad(lambda a: effort(a, x0s[0])[0])(1.0)
    assert abs(float(alone)) > 1e-3
    h = 1e-5  # the converged problem's own derivative: central differences
    fd = (effort(1.0 + h, x0s[0])[0] - effort(1.0 - h, x0s[0])[0]) / (2 * h)
    assert float(alone) == pytest.approx(float(fd), rel=1e-6)
    assert float(jax.grad(masked)(1.0)) == pytest.approx(float(alone), rel=1e-12)

    def effort_from(u_init):  # the stopped solve depends on its start: that raises too
        mpc = MPC(Pendulum(dt=0.1, length=1.0), QuadraticCost.tracking(
            jnp.eye(3), jnp.array([1.0, 0.0, 0.0])), 6, gradient="implicit", max_iter=2)
        return jnp.sum(mpc(x0s[1], u_init).u ** 2)

    match = r"MPC\(gradient='implicit'\): cannot differentiate the solution"
    with pytest.raises(Exception, match=match):  # it was 0
        jax.block_until_ready(jax.grad(effort_from)(jnp.zeros((6, 1))))


def test_implicit_gradient_at_a_stationary_point_that_is_not_a_minimum_raises():
    """Stage cost ½x² + ½(u² − 1)² from u = 0, x0 = 0: the gradient is zero at once, so MPC
    stops there (status converged), at a maximum in u. The implicit derivative does not
    exist (Q_uu = −2 < 0); it was NaN, silently, in reverse and forward mode. Now an error
    names the cause; the unrolled derivative (of the iterates) stays available."""
    from jaxpose.control import FunctionCost
    from jaxpose.dynamics import NLS

    class Scalar(NLS):
        a: jax.Array

        def state_transition(self, x, u, t=0):
            return self.a * x + u

    cost = FunctionCost(lambda x, u, t: 0.5 * jnp.sum(x**2) + 0.5 * jnp.sum((u**2 - 1.0) ** 2),
                        lambda x: 0.5 * jnp.sum(x**2))

    def total_u(a, x0, gradient="implicit"):
        sol = MPC(Scalar(a), cost, 4, gradient=gradient)(x0, jnp.zeros((4, 1)))
        return sol.u.sum(), sol.status

    a, x0 = jnp.asarray(1.0), jnp.zeros(1)
    u, status = total_u(a, x0)
    assert float(u) == 0.0 and int(status) == 0  # converged, at the stationary maximum
    match = r"MPC: cannot differentiate the solution.*not positive definite.*unroll"
    with pytest.raises(Exception, match=match):
        jax.block_until_ready(jax.grad(lambda a, x: total_u(a, x)[0], (0, 1))(a, x0))
    with pytest.raises(Exception, match=match):
        jax.block_until_ready(jax.jvp(lambda x: total_u(a, x)[0], (x0,), (jnp.ones(1),))[1])
    g = jax.grad(lambda a, x: total_u(a, x, "unroll")[0], (0, 1))(a, x0)
    assert np.all(np.isfinite(np.concatenate([np.ravel(g[0]), np.ravel(g[1])])))

    # in a batch, such a problem raises only where its derivative is used: a loss that
    # masks it out has the other problem's own gradient (it raised for the whole batch)
    def batch(a):
        def one(x0, u0):
            sol = MPC(Scalar(a), cost, 4)(x0, jnp.full((4, 1), u0))
            return sol.u.sum(), sol.status
        return jax.vmap(one)(jnp.array([[0.0], [1.0]]), jnp.array([0.0, 0.5]))

    u, status = batch(a)
    assert status.tolist() == [0, 0] and float(u[0]) == 0.0  # both converged
    alone = lambda a: MPC(Scalar(a), cost, 4)(jnp.ones(1), jnp.full((4, 1), 0.5)).u.sum()
    h = 1e-6
    fd = (alone(a + h) - alone(a - h)) / (2 * h)
    masked = jax.jit(jax.grad(lambda a: jnp.sum(jnp.where(jnp.arange(2) == 1, batch(a)[0], 0))))
    assert float(masked(a)) == pytest.approx(float(fd), rel=1e-8)
    with pytest.raises(Exception, match=match):
        jax.block_until_ready(jax.grad(lambda a: jnp.sum(batch(a)[0]))(a))


def test_closed_loop_rejects_non_system_plant_and_non_mpc():
    # a plant that is not a System was an AttributeError from inside the scan
    A, B = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]])
    mpc = MPC(LTI(A, B), QuadraticCost(np.eye(3)), 3)
    with pytest.raises(TypeError, match=r"closed_loop\(plant\): expected a .*System"):
        closed_loop(mpc, "plant", np.ones(2), 3)
    with pytest.raises(TypeError, match=r"closed_loop\(mpc\): expected a jaxpose\.control\.MPC"):
        closed_loop(LTI(A, B), LTI(A, B), np.ones(2), 3)


def test_ilqr_while_loop_differentiates_forward_and_names_reverse_alternatives():
    """ilqr(unroll=False) stops at convergence in a while_loop: jacfwd of its iterates
    equals reverse mode through the unrolled iterations (the same 20-iteration solve), and
    reverse mode raises naming unroll=True, implicit MPC and forward mode (it was JAX's
    while_loop error)."""
    from jaxpose.control import ilqr

    cost = QuadraticCost.tracking(jnp.eye(3), jnp.array([1.0, 0.0, 0.0]))

    def total_u(length, unroll=False):
        return jnp.sum(ilqr(Pendulum(dt=0.1, length=length), cost, jnp.array([0.2, -0.5]),
                            jnp.zeros((6, 1)), max_iter=20, unroll=unroll).u)

    fwd = jax.jacfwd(total_u)(1.0)
    np.testing.assert_allclose(fwd, jax.grad(lambda a: total_u(a, True))(1.0), rtol=1e-9)
    with pytest.raises(NotImplementedError, match=r"ilqr\(unroll=False\): reverse-mode.*"
                                                  r"unroll=True.*gradient='implicit'"):
        jax.grad(total_u)(1.0)
