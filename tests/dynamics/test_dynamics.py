"""Systems, linearisation, rollouts and integrators against plain-numpy references."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.control import QuadraticCost
from jaxpose.dynamics import (
    LTI,
    LTV,
    NLS,
    Bicycle,
    CartPole,
    Discretized,
    Pendulum,
    euler_step,
    integrate,
    rk4_step,
    rollout,
)
from jaxpose.lie import SE2

RNG = np.random.default_rng(0)


def _lti(n=3, m=2, p=2, dtype=np.float64):
    A = np.eye(n) + 0.1 * RNG.normal(size=(n, n))
    B = RNG.normal(size=(n, m))
    C = RNG.normal(size=(p, n))
    D = RNG.normal(size=(p, m))
    c1, c2 = RNG.normal(size=n), RNG.normal(size=p)
    return [a.astype(dtype) for a in (A, B, C, D, c1, c2)]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_lti_transition_observation_and_rollout(dtype):
    A, B, C, D, c1, c2 = _lti(dtype=dtype)
    sys = LTI(A, B, C, D, c1, c2)
    x0 = RNG.normal(size=3).astype(dtype)
    us = RNG.normal(size=(6, 2)).astype(dtype)
    xs, ys = jax.jit(lambda x, u: rollout(sys, x, u))(x0, us)
    x, ref_x, ref_y = x0.astype(np.float64), [x0], []
    for u in us:
        ref_y.append(C @ x + D @ u + c2)
        x = A @ x + B @ u + c1
        ref_x.append(x)
    tol = 1e-12 if dtype == np.float64 else 1e-5
    assert xs.dtype == dtype and xs.shape == (7, 3) and ys.shape == (6, 2)
    np.testing.assert_allclose(xs, np.array(ref_x), rtol=tol, atol=tol)
    np.testing.assert_allclose(ys, np.array(ref_y), rtol=tol, atol=tol)
    # __call__ returns (next state, observation of the current state)
    xn, y = eqx.filter_jit(sys)(x0, us[0])
    np.testing.assert_allclose(xn, xs[1], rtol=tol)
    np.testing.assert_allclose(y, ys[0], rtol=tol)


def test_rollout_batched_matches_loop():
    sys = LTI(*_lti())
    x0 = RNG.normal(size=(4, 3))
    us = RNG.normal(size=(4, 5, 2))
    run = jax.jit(lambda x, u: rollout(sys, x, u))
    xs, ys = run(x0, us)
    assert xs.shape == (4, 6, 3) and ys.shape == (4, 5, 2)
    one = jax.jit(lambda x, u: rollout(sys, x, u))
    for i in range(4):
        xi, yi = one(x0[i], us[i])
        np.testing.assert_allclose(xs[i], xi, rtol=1e-13)
        np.testing.assert_allclose(ys[i], yi, rtol=1e-13)
    xs_shared, _ = jax.jit(lambda x, u: rollout(sys, x, u))(x0, us[0])  # inputs broadcast
    np.testing.assert_allclose(xs_shared[2], one(x0[2], us[0])[0], rtol=1e-13)


def test_ltv_indexes_time():
    T, n, m = 4, 2, 1
    A = np.eye(n) + 0.1 * RNG.normal(size=(T, n, n))
    B = RNG.normal(size=(T, n, m))
    sys = LTV(A, B)
    x0 = RNG.normal(size=n)
    us = RNG.normal(size=(T, m))
    xs, _ = jax.jit(lambda x, u: rollout(sys, x, u))(x0, us)
    x = x0
    for t in range(T):
        x = A[t] @ x + B[t] @ us[t]
    np.testing.assert_allclose(xs[-1], x, rtol=1e-13)
    lin = sys.linearize(np.zeros((3, n)), np.zeros(m), t=np.array([0, 2, 3]))
    np.testing.assert_allclose(lin.A[1], A[2])
    assert sys.horizon == T


def test_ltv_negative_step_raises_instead_of_wrapping():
    """``A[-1]`` is the last step in JAX: a negative t silently used it. Now a ValueError
    (eagerly) or eqx.error_if (traced t); t within [0, T) indexes as before."""
    T, n, m = 3, 2, 1
    A = np.eye(n) + 0.1 * RNG.normal(size=(T, n, n))
    B = RNG.normal(size=(T, n, m))
    sys = LTV(A, B)
    x, u = RNG.normal(size=n), RNG.normal(size=m)
    with pytest.raises(ValueError, match="t: expected a time step index >= 0"):
        sys.state_transition(x, u, -1)
    with pytest.raises(ValueError, match="t: expected a time step index >= 0"):
        sys.linearize(np.zeros((2, n)), np.zeros(m), t=np.array([1, -2]))
    step = jax.jit(lambda t: sys.state_transition(x, u, t))
    with pytest.raises(RuntimeError, match="t: expected a time step index >= 0"):
        jax.block_until_ready(step(-1))  # an accelerator raises when the result is read
    np.testing.assert_allclose(step(1), A[1] @ x + B[1] @ u, rtol=1e-13)


def test_ltv_fractional_or_late_step_raises_instead_of_truncating_or_clamping():
    """t = 1.7 silently used step 1 (an int32 cast) and t = T the last step (JAX clamps
    gathers); integral floats still index."""
    T, n, m = 3, 2, 1
    A = np.eye(n) + 0.1 * RNG.normal(size=(T, n, n))
    B = RNG.normal(size=(T, n, m))
    sys = LTV(A, B)
    x, u = RNG.normal(size=n), RNG.normal(size=m)
    message = r"t: expected a time step index >= 0 and < 3 \(the LTV system's 3 time steps\)"
    for t in (1.7, 3, 10):
        with pytest.raises(ValueError, match=message):
            sys.state_transition(x, u, t)
    with pytest.raises(ValueError, match=message):
        sys.linearize(np.zeros((2, n)), np.zeros(m), t=np.array([1.0, 1.5]))
    step = jax.jit(lambda t: sys.state_transition(x, u, t))
    for t in (1.5, 3):
        with pytest.raises(RuntimeError, match=message):
            jax.block_until_ready(step(t))
    np.testing.assert_allclose(step(2.0), A[2] @ x + B[2] @ u, rtol=1e-13)
    cost = QuadraticCost(np.stack([np.eye(n + m)] * T))
    with pytest.raises(ValueError, match=r"t: expected .* and < 3 \(the cost's 3 time steps\)"):
        cost.stage(x, u, T)


def test_benchmark_models_check_state_and_input_sizes():
    """Extra input components were silently ignored (u[1] of the 1-input pendulum) and a
    scalar u gave an IndexError; sizes are shapes, so the check also runs under jit."""
    cases = [
        (Pendulum(), 2, 1, "Pendulum"),
        (CartPole(), 4, 1, "CartPole"),
        (Bicycle(), 4, 2, "Bicycle"),
    ]
    for model, n, m, name in cases:
        x, u = jnp.zeros(n), jnp.zeros(m)
        for bad_u in (jnp.zeros(m + 1), jnp.array(1.0)):
            with pytest.raises(ValueError, match=rf"u: expected last dimension {m} \({name}"):
                model.state_transition(x, bad_u)
            with pytest.raises(ValueError, match=rf"u: expected last dimension {m} \({name}"):
                eqx.filter_jit(model.state_transition)(x, bad_u)
        with pytest.raises(ValueError, match=rf"x: expected last dimension {n} \({name}"):
            model.state_transition(jnp.zeros(n + 1), u)
        assert model.state_transition(x, u).shape == (n,)
    with pytest.raises(ValueError, match=r"u: expected last dimension 2 \(Bicycle inputs"):
        Bicycle().observation(jnp.zeros(4), jnp.zeros(3))


def test_bicycle_ranges_exact_and_differentiable_at_a_landmark():
    """sqrt(Σd²) had a NaN Jacobian on a landmark (the default landmarks include the
    origin). Values stay exact; the derivative is d/|d| away from it (closed form and
    central differences) and the subgradient 0 on it, in forward and reverse mode."""
    model = Bicycle()
    L = np.asarray(model.landmarks)
    h = jax.jit(lambda x: model.observation(x, jnp.zeros(2)))
    for x in (np.array([3.0, -2.0, 0.4, 1.5]), np.array([19.0, 0.5, -1.0, 0.2])):
        d = x[:2] - L
        r = np.hypot(d[:, 0], d[:, 1])
        np.testing.assert_allclose(h(x), np.r_[r, x[3]], rtol=1e-15)
        J = np.zeros((5, 4))
        J[:4, :2], J[4, 3] = d / r[:, None], 1.0
        np.testing.assert_allclose(jax.jacfwd(h)(x), J, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(jax.jacrev(h)(x), J, rtol=1e-13, atol=1e-15)
        eps, E = 1e-6, np.eye(4)
        fd = np.stack([(h(x + eps * e) - h(x - eps * e)) / (2 * eps) for e in E], -1)
        np.testing.assert_allclose(jax.jacfwd(h)(x), fd, atol=1e-8)
    x = np.array([20.0, 20.0, 0.3, 1.0])  # on landmark 3
    y = np.asarray(h(x))
    assert y[3] == 0.0
    for jac in (jax.jacfwd(h), jax.jacrev(h)):
        J = np.asarray(jac(x))
        assert np.all(np.isfinite(J)) and np.all(J[3] == 0.0)
        np.testing.assert_allclose(J[:3, :2], (x[:2] - L[:3]) / y[:3, None], rtol=1e-13)
    # a NaN position gives NaN ranges (the hand-written double where returned 0 for them)
    y = np.asarray(h(np.array([np.nan, 1.0, 0.0, 2.0])))
    assert np.all(np.isnan(y[:4])) and y[4] == 2.0


def _pendulum_rk4_numpy(x, u, dt=0.05, g=9.81, length=1.0, mass=1.0, b=0.1):
    def f(s):
        return np.array([s[1], -(g / length) * np.sin(s[0]) - b * s[1] + u / (mass * length**2)])

    k1 = f(x)
    k2 = f(x + 0.5 * dt * k1)
    k3 = f(x + 0.5 * dt * k2)
    k4 = f(x + dt * k3)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def test_pendulum_step_matches_numpy_rk4():
    x = np.array([0.5, -0.3])
    np.testing.assert_allclose(
        Pendulum().state_transition(jnp.asarray(x), jnp.array([0.7])),
        _pendulum_rk4_numpy(x, 0.7), rtol=1e-13)


class Pend(NLS):
    """Euler-discretised pendulum with a learnable length; observes sin θ."""

    length: jax.Array

    def state_transition(self, x, u, t=0):
        th, om = x[0], x[1]
        return jnp.stack([th + 0.05 * om, om + 0.05 * (-9.81 / self.length * jnp.sin(th) + u[0])])

    def observation(self, x, u, t=0):
        return jnp.stack([jnp.sin(x[0]), x[1] * u[0]])


def test_nls_linearize_per_element():
    sys = Pend(jnp.asarray(1.3))
    xs = RNG.normal(size=(5, 2))
    us = RNG.normal(size=(5, 1))
    lin = eqx.filter_jit(sys.linearize)(xs, us)
    assert lin.A.shape == (5, 2, 2) and lin.B.shape == (5, 2, 1) and lin.C.shape == (5, 2, 2)
    for i in range(5):
        th, om = xs[i]
        A = np.array([[1, 0.05], [-0.05 * 9.81 / 1.3 * np.cos(th), 1]])
        np.testing.assert_allclose(lin.A[i], A, rtol=1e-13)
        np.testing.assert_allclose(lin.B[i], [[0], [0.05]], atol=1e-15)
        np.testing.assert_allclose(lin.C[i], [[np.cos(th), 0], [0, us[i, 0]]], rtol=1e-13)
        np.testing.assert_allclose(lin.D[i], [[0], [om]], rtol=1e-13)
        # affine model reproduces f and h at the reference point
        f, h = sys(xs[i], us[i])
        np.testing.assert_allclose(lin.A[i] @ xs[i] + lin.B[i] @ us[i] + lin.c1[i], f, rtol=1e-12)
        np.testing.assert_allclose(lin.C[i] @ xs[i] + lin.D[i] @ us[i] + lin.c2[i], h, rtol=1e-12)


def test_nls_differentiable_wrt_parameters():
    x0, us = jnp.array([0.4, 0.0]), jnp.zeros((20, 1))

    def loss(length):
        xs, _ = rollout(Pend(length), x0, us)
        return jnp.sum(xs[:, 0] ** 2)

    _, g = jax.jit(jax.value_and_grad(loss))(1.3)
    eps = 1e-6
    lp, lm = jax.jit(jax.vmap(loss))(jnp.array([1.3 + eps, 1.3 - eps]))
    np.testing.assert_allclose(g, (lp - lm) / (2 * eps), rtol=1e-6)
    # and through a linearisation (d A / d length)
    dA = jax.jit(jax.jacfwd(lambda ln: Pend(ln).linearize(x0, us[0]).A))(1.3)
    np.testing.assert_allclose(dA[1, 0], 0.05 * 9.81 / 1.3**2 * np.cos(0.4), rtol=1e-12)


def test_integrator_orders():
    f = lambda x, u, tau: -x + u
    x0, u = jnp.array([1.0]), jnp.array([0.0])
    exact = lambda h: np.exp(-h)
    errs_e, errs_r = [], []
    for h in (0.1, 0.05):
        errs_e.append(abs(float(euler_step(f, x0, u, 0.0, h)[0]) - exact(h)))
        errs_r.append(abs(float(rk4_step(f, x0, u, 0.0, h)[0]) - exact(h)))
    assert 3.5 < errs_e[0] / errs_e[1] < 4.5  # local error O(h²)
    assert 28 < errs_r[0] / errs_r[1] < 36  # local error O(h⁵)
    # substeps and time dependence: ẋ = τ → x(τ) = τ²/2 exactly for RK4
    g = lambda x, u, tau: jnp.atleast_1d(tau)
    np.testing.assert_allclose(integrate(g, jnp.zeros(1), u, 1.0, 0.5, "rk4", 3), [0.625])
    with pytest.raises(ValueError, match="method"):
        integrate(f, x0, u, 0.0, 0.1, "midpoint")


def test_continuous_models_and_discretized():
    cp = CartPole(dt=0.02)
    x = jnp.array([0.0, 0.0, 0.2, 0.0])
    xn = eqx.filter_jit(cp.state_transition)(x, jnp.array([0.0]), 0)
    assert xn[2] > 0.2  # falls away from upright
    d = Discretized(lambda x, u, tau: jnp.stack([x[1], -x[0]]), dt=0.1, method="euler")
    np.testing.assert_allclose(d.state_transition(jnp.array([1.0, 0.0]), None), [1.0, -0.1])
    pend = Pendulum(dt=0.05)
    g = jax.jit(
        jax.grad(
            lambda ln: eqx.tree_at(lambda p: p.length, pend, ln).state_transition(
                jnp.array([0.3, 0.0]), jnp.zeros(1), 0
            )[1]
        )
    )(1.0)
    assert np.isfinite(g) and g > 0
    with pytest.raises(ValueError, match="method"):
        Discretized(lambda x, u, t: x, dt=0.1, method="rk45")


def test_group_state_rollout():
    class Odometry(NLS):
        def state_transition(self, X, u, t=0):
            return X @ SE2.exp(u)

        def observation(self, X, u, t=0):
            return X.translation()

    X0 = SE2.identity()
    us = jnp.tile(jnp.array([1.0, 0.0, np.pi / 2]), (4, 1))
    Xs, ys = rollout(Odometry(), X0, us)
    assert isinstance(Xs, SE2) and Xs.shape == (5,)
    np.testing.assert_allclose(Xs[-1].data, SE2.identity().data, atol=1e-12)  # a closed square


def test_bad_input_errors():
    A, B, C, D, c1, c2 = _lti()
    with pytest.raises(ValueError, match="A: expected a square"):
        LTI(np.ones((3, 2)), B)
    with pytest.raises(ValueError, match=r"B: expected shape \(3, m\)"):
        LTI(A, np.ones((2, 2)))
    with pytest.raises(ValueError, match="C: expected shape"):
        LTI(A, B, np.ones((2, 4)))
    with pytest.raises(ValueError, match="D: expected shape"):
        LTI(A, B, C, np.ones((2, 3)))
    with pytest.raises(ValueError, match="c1: expected shape"):
        LTI(A, B, c1=np.ones(2))
    with pytest.raises(TypeError, match="A: expected an array"):
        LTI("A", B)
    sys = LTI(A, B)
    with pytest.raises(ValueError, match=r"x: expected last dimension 3"):
        sys.state_transition(np.ones(4), np.ones(2))
    with pytest.raises(ValueError, match=r"u: expected last dimension 2"):
        sys.state_transition(np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match="us: expected inputs"):
        rollout(sys, np.ones(3), np.ones(2))
    with pytest.raises(ValueError, match="B: expected 4 time steps"):
        LTV(np.ones((4, 2, 2)), np.ones((3, 2, 1)))


def test_matrices_and_linearize_check_their_arguments():
    """Found by an audit (session 48): LTV.matrices(-2) sliced A[0:-2] (a 1-step window of
    a 3-step system), LTI.matrices(-2) was a raw broadcast error, and linearize accepted
    inputs of any size where state_transition refuses them."""
    A, B = np.eye(2), np.ones((2, 1))
    ltv = LTV(np.stack([A] * 3), np.stack([B] * 3))
    for system in (LTI(A, B), ltv):
        for bad in (0, -2):
            with pytest.raises(ValueError, match="horizon: expected an int >= 1"):
                system.matrices(bad)
        with pytest.raises(TypeError, match="horizon: expected an int >= 1"):
            system.matrices(2.0)
        with pytest.raises(ValueError, match=r"x: expected last dimension 2"):
            system.linearize(np.ones(5), np.ones(1))
        with pytest.raises(ValueError, match=r"u: expected last dimension 1"):
            system.linearize(np.ones(2), np.ones(4))
    assert ltv.matrices(2, t0=1)[0].shape == (2, 2, 3)


@pytest.mark.parametrize("kw, match", [
    ({"dt": 0.0}, "dt: expected a positive time step"),
    ({"dt": -0.1}, "dt: expected a positive time step"),
    ({"method": "rk45"}, "method: expected one of"),
    ({"substeps": 0}, "substeps: expected an int >= 1"),
])
def test_models_check_their_integration_options_at_construction(kw, match):
    """The models accepted these and failed at the first step (Discretized refused them at
    construction); a NumPy integer is a valid substep count."""
    for model in (Pendulum, CartPole, Bicycle):
        with pytest.raises(ValueError, match=match):
            model(**kw)
    with pytest.raises(ValueError, match=match):
        Discretized(lambda x, u, t: -x, **({"dt": 0.1} | kw))
    x = integrate(lambda x, u, t: -x, jnp.ones(1), jnp.zeros(1), 0.0, 0.1,
                  substeps=np.int64(2))
    np.testing.assert_allclose(x, np.exp(-0.1), rtol=1e-6)  # RK4, two steps


def test_models_refuse_known_non_positive_lengths_and_masses():
    """Pendulum(length=0) failed with a bare ZeroDivisionError at the first step; traced
    parameters (learned ones) are not checked at construction and still differentiate."""
    for model, kw in ((Pendulum, {"length": 0.0}), (Pendulum, {"mass": -1.0}),
                      (CartPole, {"length": float("nan")}), (Bicycle, {"wheelbase": 0.0})):
        with pytest.raises(ValueError, match=rf"{model.__name__}\({next(iter(kw))}=.*positive"):
            model(**kw)
    grad = jax.grad(lambda length: Pendulum(length=length).state_transition(
        jnp.ones(2), jnp.zeros(1))[1])(1.5)
    assert np.isfinite(float(grad))
