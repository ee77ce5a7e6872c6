"""Gradients through the solution: implicit and unrolled adjoints vs central differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import jaxpose.optim as jo
from jaxpose.lie import SE3
from jaxpose.results import Results

from .problems import EXP_ARGS, EXP_OPT, exp_residual

TIGHT = dict(gtol=1e-13, xtol=1e-14, cost_rtol=0.0, max_steps=60)


def _central(fn, x, eps):
    """Richardson-extrapolated central differences of fn (R^k -> R^m) at x (error
    O(eps⁴) plus solve noise / eps); all 4k evaluations in one vmap."""
    k = x.shape[0]
    pert = jnp.eye(k, dtype=x.dtype)
    steps = jnp.concatenate([eps * pert, -eps * pert, 0.5 * eps * pert, -0.5 * eps * pert])
    vals = jax.vmap(fn)(x + steps).reshape(4, k, -1)
    d1 = (vals[0] - vals[1]) / (2 * eps)
    d2 = (vals[2] - vals[3]) / eps
    return ((4 * d2 - d1) / 3).T


# --------------------------------------------------------------------------------------
# a pose + scale fit: params {SE3, scalar}, args = observed points (nonzero residual)
# --------------------------------------------------------------------------------------
_key = jax.random.PRNGKey(0)
PTS = jax.random.normal(_key, (6, 3))
TRUE = SE3.random(jax.random.PRNGKey(1), (), sigma=0.5)
OBS = 1.3 * TRUE.act(PTS) + 0.05 * jax.random.normal(jax.random.PRNGKey(2), (6, 3))
INIT = {"pose": SE3.random(jax.random.PRNGKey(3), (), sigma=0.2) @ TRUE, "k": jnp.asarray(1.0)}


def pose_residual(p, obs):
    return p["k"] * p["pose"].act(PTS) - obs


def _solution_of(adjoint):
    def f(obs_flat):
        sol = jo.least_squares(pose_residual, INIT, obs_flat.reshape(6, 3), adjoint=adjoint,
                               **TIGHT)
        return ravel_pytree(sol.params)[0]
    return f


def _pose_fd():
    # the forward solve is accurate to ~1e-11 (cost resolution), so a large step keeps the
    # difference noise (~1e-8) and the O(eps⁴) truncation well below the tolerance
    return jax.jit(lambda x: _central(_solution_of("implicit"), x, 1e-3))(OBS.reshape(-1))


def test_pose_fit_implicit_jacobian_matches_finite_differences():
    jac = jax.jit(jax.jacrev(_solution_of("implicit")))(OBS.reshape(-1))
    assert jac.shape == (8, 18)
    np.testing.assert_allclose(jac, _pose_fd(), rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_pose_fit_unrolled_jacobian_matches_finite_differences():
    jac = jax.jit(jax.jacrev(_solution_of("unrolled")))(OBS.reshape(-1))
    np.testing.assert_allclose(jac, _pose_fd(), rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------------------
# cheaper array problems: weights, kernels, closures, the cost, vmap
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("adjoint", ["implicit", "unrolled"])
def test_gradients_wrt_args_weights_and_cost_match_finite_differences(adjoint):
    # d(params*, cost*)/d(y, w) for a weighted, Cauchy-robustified fit (nonzero residual)
    t, y = EXP_ARGS

    def out(v, adjoint=adjoint):  # v = [y (20), w (20)] -> [params (2), cost]
        sol = jo.least_squares(exp_residual, jnp.asarray(EXP_OPT), (t, v[:20]),
                               weights=v[20:, None, None], kernel=jo.Cauchy(0.2),
                               adjoint=adjoint, **TIGHT)
        return jnp.concatenate([sol.params, sol.cost[None]])

    v = jnp.concatenate([y, jnp.linspace(0.5, 2.0, 20)])
    jac = jax.jit(jax.jacrev(out))(v)
    fd = jax.jit(lambda v: _central(lambda u: out(u, "implicit"), v, 1e-3))(v)
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-6)


def test_gauss_newton_hessian_adjoint_is_exact_for_zero_residual():
    t, _ = EXP_ARGS
    adj = jo.ImplicitAdjoint(hessian="gauss_newton")

    def out(ab):
        y = ab[0] * jnp.exp(-ab[1] * t)  # data on the model: zero residual at the optimum
        return jo.least_squares(exp_residual, jnp.array([1.0, 1.0]), (t, y), adjoint=adj,
                                **TIGHT).params

    jac = jax.jit(jax.jacrev(out))(jnp.array([2.0, 1.3]))
    np.testing.assert_allclose(jac, np.eye(2), atol=1e-9)


def test_closed_over_values_are_differentiated():
    t, y = EXP_ARGS

    def fit(scale):
        def res(p, args):  # closes over `scale` (a tracer under grad)
            return (p[0] * jnp.exp(-p[1] * t) - scale * y)[:, None]
        sol = jo.least_squares(res, jnp.asarray(EXP_OPT), None, **TIGHT)
        return sol.params[1] + sol.params[0] ** 2

    g = jax.jit(jax.grad(fit))(1.1)
    # h = 1e-2: the truncation error is ~1e-10 here, while the solves' own stopping
    # error (~1e-11, depends on XLA's rounding) divided by a smaller h would dominate
    fd = jax.jit(lambda x: _central(lambda u: fit(u[0])[None], x, 1e-2))(jnp.array([1.1]))
    assert float(g) == pytest.approx(float(fd[0, 0]), rel=1e-7)


def test_vmap_of_grad_and_float32():
    t, y = EXP_ARGS

    def loss(y):
        sol = jo.least_squares(exp_residual, jnp.asarray(EXP_OPT, y.dtype),
                               (t.astype(y.dtype), y), max_steps=40)
        return jnp.sum(sol.params**2)

    ys = jnp.stack([y, 1.1 * y, 0.9 * y])
    batched = jax.jit(jax.vmap(jax.grad(loss)))(ys)
    single = jax.jit(jax.grad(loss))
    for i in range(3):
        np.testing.assert_allclose(batched[i], single(ys[i]), rtol=1e-10)
    # float32: the implicit gradient is finite and close to the float64 one
    g32 = jax.jit(jax.grad(loss))(y.astype(jnp.float32))
    assert g32.dtype == jnp.float32
    np.testing.assert_allclose(g32, single(y), rtol=2e-2, atol=2e-3)


_T = jnp.linspace(0.0, 2.0, 20)
_Y = 2.0 * jnp.exp(-1.3 * _T) + 0.05 * jnp.sin(7.0 * _T)


def _huber_fit_loss(y, adjoint):
    """Issue 16's case: Σ p² of a Huber fit of p0·exp(−p1·t) to y."""

    def residual(p, y):
        return (p[0] * jnp.exp(-p[1] * _T) - y)[:, None]

    sol = jo.least_squares(residual, jnp.array([1.0, 0.5]), y, kernel=jo.Huber(0.5),
                           adjoint=adjoint)
    return jnp.sum(sol.params ** 2)


def _richardson_row(grad, y, i, eps=1e-3):
    """Row i of the Hessian by Richardson-extrapolated central differences of ``grad``."""
    e = jnp.zeros_like(y).at[i].set(eps)
    d1 = (grad(y + e) - grad(y - e)) / (2 * eps)
    d2 = (grad(y + e / 2) - grad(y - e / 2)) / eps
    return (4 * d2 - d1) / 3


def test_second_derivative_through_implicit_adjoint_matches_finite_differences():
    """Issue 16's case: jacfwd(jacrev) through the implicit adjoint (Huber kernel) gave
    0.017746 where finite differences give 0.017514 (the backward pass held the solution's
    dependence on y fixed). The custom_jvp rule is differentiable, so it is exact now."""
    loss, y = _huber_fit_loss, _Y
    grad = jax.jit(jax.grad(loss), static_argnums=1)
    np.testing.assert_allclose(grad(y, "implicit"), grad(y, "unrolled"), rtol=1e-5, atol=1e-6)
    hess = jax.jit(jax.jacfwd(jax.jacrev(loss)), static_argnums=1)(y, "implicit")
    for i in (3, 11):
        fd = _richardson_row(lambda v: grad(v, "implicit"), y, i)
        np.testing.assert_allclose(hess[i], fd, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(hess, hess.T, atol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.hessian(loss), static_argnums=1)(y, "implicit"),
                               hess, atol=1e-12)


def _root_mean_cube(y, dtype=jnp.float64):
    """f(y) = p*³ where p* minimises ½Σ(p² − yᵢ)²: p*² = mean(y), so f = mean(y)^{3/2} —
    a nonlinear fit with nonzero residuals and a closed-form derivative of every order."""
    sol = jo.least_squares(lambda p, y: (p[0] ** 2 - y)[:, None], jnp.ones(1, dtype), y,
                           gtol=1e-15, xtol=1e-16, cost_rtol=0.0, max_steps=80)
    return sol.params[0] ** 3


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_implicit_derivatives_of_every_order_equal_the_closed_form(dtype):
    y = jnp.array([1.0, 1.5, 2.5, 3.0], dtype)
    n, m = 4, float(jnp.mean(y.astype(jnp.float64)))
    rtol = 1e-10 if dtype == jnp.float64 else 2e-5  # the solve stops within ~1e-11
    f = jax.jit(_root_mean_cube)
    np.testing.assert_allclose(f(y), m**1.5, rtol=rtol)
    d1 = np.full(n, 1.5 * m**0.5 / n)
    d2 = np.full((n, n), 0.75 * m**-0.5 / n**2)
    d3 = np.full((n, n, n), -0.375 * m**-1.5 / n**3)
    np.testing.assert_allclose(jax.jit(jax.grad(f))(y), d1, rtol=rtol)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(f))(y), d1, rtol=rtol)
    _, jv = jax.jit(lambda y, t: jax.jvp(f, (y,), (t,)))(y, jnp.ones_like(y))
    np.testing.assert_allclose(jv, d1.sum(), rtol=rtol)
    hess = jax.jit(jax.hessian(f))(y)
    assert hess.dtype == dtype
    np.testing.assert_allclose(hess, d2, rtol=rtol)
    np.testing.assert_allclose(jax.jit(jax.jacrev(jax.jacrev(f)))(y), d2, rtol=rtol)
    if dtype == jnp.float64:
        np.testing.assert_allclose(jax.jit(jax.jacfwd(jax.jacfwd(jax.jacrev(f))))(y), d3,
                                   rtol=1e-10)
        batch = jnp.stack([y, 2.0 * y])
        hb = jax.jit(jax.vmap(jax.hessian(f)))(batch)
        np.testing.assert_allclose(hb[1], np.full((n, n), 0.75 * (2 * m) ** -0.5 / n**2),
                                   rtol=rtol)


@pytest.mark.parametrize("solver", [jo.Cholesky(), jo.LU(), jo.CG()],
                         ids=lambda s: type(s).__name__)
def test_other_adjoint_solvers_are_exact_at_every_order(solver):
    """An adjoint solver other than the default SVD runs inside custom_linear_solve: its
    derivatives of orders 1–3 equal the closed form of :func:`_root_mean_cube`."""
    adj = jo.ImplicitAdjoint(linear_solver=solver)

    def f(y):
        sol = jo.least_squares(lambda p, y: (p[0] ** 2 - y)[:, None], jnp.ones(1), y,
                               adjoint=adj, gtol=1e-15, xtol=1e-16, cost_rtol=0.0, max_steps=80)
        return sol.params[0] ** 3

    y = jnp.array([1.0, 1.5, 2.5, 3.0])
    n, m = 4, float(jnp.mean(y))
    np.testing.assert_allclose(jax.jit(jax.grad(f))(y), np.full(n, 1.5 * m**0.5 / n),
                               rtol=1e-10)
    np.testing.assert_allclose(jax.jit(jax.hessian(f))(y),
                               np.full((n, n), 0.75 * m**-0.5 / n**2), rtol=1e-10)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(jax.jacfwd(jax.jacrev(f))))(y),
                               np.full((n, n, n), -0.375 * m**-1.5 / n**3), rtol=1e-10)


def test_an_adjoint_solve_that_fails_raises_instead_of_a_nan_derivative():
    """At a stationary maximum (½[(p² − 1)² + (p − z)²] from p = 0, z = 0: H = −1) the
    Cholesky adjoint fails; with a gauge freedom (p₁ unobserved: H singular) so do LU and
    Cholesky. Forward mode returned NaN silently, reverse mode raised lineax's generic
    message; both now raise naming the cause. The default SVD adjoint gives the
    minimum-norm derivative of the gauge problem (dp₀/dz = 1, dp₁/dz = 0)."""
    def solution_sum(residual, p0, solver):
        adj = jo.ImplicitAdjoint(linear_solver=solver)
        return lambda z: jo.least_squares(residual, p0, z, adjoint=adj).params.sum()

    maximum = lambda p, z: jnp.stack([p[0] ** 2 - 1.0, p[0] - z])  # noqa: E731
    gauge = lambda p, z: jnp.stack([p[0] - z])  # noqa: E731
    match = r"least_squares: cannot differentiate the solution.*Hessian H at the solution"
    for residual, p0, solver in ((maximum, jnp.zeros(1), jo.Cholesky()),
                                 (gauge, jnp.zeros(2), jo.LU()),
                                 (gauge, jnp.zeros(2), jo.Cholesky())):
        f = solution_sum(residual, p0, solver)
        with pytest.raises(Exception, match=match):
            jax.block_until_ready(jax.grad(f)(jnp.asarray(0.0)))
        with pytest.raises(Exception, match=match):
            jax.block_until_ready(jax.jvp(f, (jnp.asarray(0.0),), (jnp.asarray(1.0),))[1])
    f = solution_sum(gauge, jnp.zeros(2), jo.SVD())
    assert float(jax.grad(f)(jnp.asarray(1.0))) == pytest.approx(1.0, rel=1e-12)


def test_gauss_newton_adjoint_refuses_a_second_derivative():
    """J̃ᵀJ̃ drops the Hessian's residual terms: first order is exact for zero residuals
    only, and a second derivative would be wrong, so it raises."""
    adj = jo.ImplicitAdjoint(hessian="gauss_newton")

    def f(y):
        sol = jo.least_squares(lambda p, y: (p[0] ** 2 - y)[:, None], jnp.ones(1), y,
                               adjoint=adj, **TIGHT)
        return sol.params[0] ** 3

    y = jnp.array([1.0, 1.5, 2.5, 3.0])
    assert np.all(np.isfinite(jax.grad(f)(y)))
    with pytest.raises(NotImplementedError, match=r"gauss_newton.*first order"):
        jax.hessian(f)(y)


@pytest.mark.slow  # a Hessian through an SE3 fit compiles for ~20 s
def test_pose_fit_implicit_hessian_matches_finite_differences():
    w = jax.random.normal(jax.random.PRNGKey(5), (8,))

    def loss(obs_flat):
        sol = jo.least_squares(pose_residual, INIT, obs_flat.reshape(6, 3), **TIGHT)
        return jnp.dot(w, ravel_pytree(sol.params)[0]) + sol.cost

    x = OBS.reshape(-1)
    hess = jax.jit(jax.jacfwd(jax.jacrev(loss)))(x)
    grad = jax.jit(jax.grad(loss))
    for i in (0, 7):
        np.testing.assert_allclose(hess[i], _richardson_row(grad, x, i), rtol=1e-6, atol=1e-7)


@pytest.mark.slow  # an eager Hessian through the unrolled LM loop (minutes of tracing)
def test_second_derivative_through_unrolled_adjoint_matches_finite_differences():
    """The unrolled adjoint gives the second derivative too (one Hessian row against
    central differences of the gradient)."""
    loss, y = _huber_fit_loss, _Y
    e = jnp.zeros_like(y).at[3].set(1e-5)
    hess = jax.jacfwd(jax.jacrev(loss))(y, "unrolled")
    gp, gm = jax.grad(loss)(y + e, "unrolled"), jax.grad(loss)(y - e, "unrolled")
    np.testing.assert_allclose(hess[3], (gp - gm) / 2e-5, rtol=1e-3, atol=1e-5)


def test_derivative_of_an_unconverged_solution_raises():
    """A solve stopped by its budget is not at a stationary point: the implicit derivative
    there is neither the optimum's nor the steps' (on pose3example with Huber it was 100x
    off), so forward and reverse mode raise, also for one unconverged problem of a vmapped
    batch; with enough steps the same call differentiates."""
    t, y = EXP_ARGS

    def rate(y, steps):
        return jo.least_squares(exp_residual, jnp.array([1.0, 0.5]), (t, y),
                                max_steps=steps).params[1]

    match = "least_squares: cannot differentiate the solution: the solver stopped without"
    few = jax.jit(lambda y: rate(y, 2))
    assert int(jo.least_squares(exp_residual, jnp.array([1.0, 0.5]), (t, y),
                                max_steps=2).status) == 1  # max_steps
    with pytest.raises(Exception, match=match):
        jax.block_until_ready(jax.grad(few)(y))
    with pytest.raises(Exception, match=match):
        jax.block_until_ready(jax.jvp(few, (y,), (jnp.ones_like(y),))[1])
    starts = jnp.array([[1.0, 0.5], [1.0, 20.0]])  # 6 and 24 steps to converge

    def batched(y, steps):
        return jax.vmap(lambda p0: jo.least_squares(exp_residual, p0, (t, y),
                                                     max_steps=steps).params[1])(starts).sum()

    with pytest.raises(Exception, match=match):  # problem 0 converges, problem 1 cannot
        jax.block_until_ready(jax.grad(batched)(y, 8))
    assert np.isfinite(float(jax.grad(batched)(y, 40).sum()))
    assert np.isfinite(float(jax.grad(lambda y: rate(y, 40))(y).sum()))


def _square_residual(p, a):
    return jnp.stack([p[0] ** 2 - a[0], 0.1 * p[1] - a[1]])


@pytest.mark.parametrize("linear_solver", [jo.SVD(), jo.Cholesky()])
def test_an_unconverged_problem_masked_out_of_a_batch_does_not_block_its_derivative(
        linear_solver):
    """One Gauss-Newton step: problem 0 starts near its optimum and converges, problem 1
    stops (max_steps) where its Hessian is indefinite (eigenvalues −1.46, 0.01). A loss
    that masks problem 1 out has the gradient of problem 0 alone; it raised "cannot
    differentiate" for the whole batch (the check saw the status, not the cotangent), and
    with Cholesky the masked problem's indefinite H failed the adjoint's solve. Problem 0's
    gradient: d(p0 + p1 + cost)/da = (1/(2 p0), 10) at p = (1, 10 a1) = (0.5, 10). Forward
    mode still raises (the masked problem's tangent is computed either way)."""
    a = jnp.array([1.0, 0.3])
    starts = jnp.array([[1.0, 2.9], [0.3, 1.0]])
    adjoint = jo.ImplicitAdjoint(linear_solver=linear_solver)

    def per_problem(a):
        sols = jax.vmap(lambda p0: jo.least_squares(
            _square_residual, p0, a, solver=jo.GaussNewton(), max_steps=1,
            adjoint=adjoint))(starts)
        return sols.params.sum(-1) + sols.cost, sols.status

    values, status = per_problem(a)
    assert status.tolist() == [Results.CONVERGED, Results.MAX_STEPS]

    def masked(a):
        values, status = per_problem(a)
        return jnp.sum(jnp.where(status == Results.CONVERGED, values, 0.0))

    np.testing.assert_allclose(jax.jit(jax.grad(masked))(a), [0.5, 10.0], rtol=1e-12)
    np.testing.assert_allclose(jax.jacrev(lambda a: per_problem(a)[0][0])(a), [0.5, 10.0],
                               rtol=1e-12)
    match = "least_squares: cannot differentiate the solution"
    with pytest.raises(Exception, match=match):  # unmasked
        jax.block_until_ready(jax.grad(lambda a: per_problem(a)[0].sum())(a))
    with pytest.raises(Exception, match=match):  # forward mode computes its tangent anyway
        jax.block_until_ready(jax.jacfwd(masked)(a))


def test_derivative_with_respect_to_the_start_of_an_unconverged_solve_raises():
    """One Gauss-Newton step stops (max_steps) where the iterate depends on the start (the
    unrolled derivative is the identity); jvp, jacfwd, jacrev and hessian with respect
    to the start returned 0 (the check saw only the data's tangent). Converged, the
    derivative with respect to the start is exactly 0."""
    a = jnp.array([1.0, 0.3])

    def params(p0, steps):
        return jo.least_squares(_square_residual, p0, a, solver=jo.GaussNewton(),
                                max_steps=steps).params

    start = jnp.array([0.3, 1.0])
    assert int(jo.least_squares(_square_residual, start, a, solver=jo.GaussNewton(),
                                max_steps=1).status) == Results.MAX_STEPS
    def cost(p0):
        return jo.least_squares(_square_residual, p0, a, solver=jo.GaussNewton(),
                                max_steps=1).cost

    match = "least_squares: cannot differentiate the solution"
    for call in (lambda: jax.jvp(lambda p: params(p, 1), (start,), (jnp.ones(2),))[1],
                 lambda: jax.jacfwd(lambda p: params(p, 1))(start),
                 lambda: jax.jacrev(lambda p: params(p, 1))(start),
                 lambda: jax.jit(jax.grad(cost))(start)):
        with pytest.raises(Exception, match=match):
            jax.block_until_ready(call())
    np.testing.assert_array_equal(jax.jacrev(lambda p: params(p, 50))(start), 0.0)
    np.testing.assert_array_equal(jax.jacfwd(lambda p: params(p, 50))(start), 0.0)


def _rosenbrock_residual(p, a):
    return jnp.stack([10 * (p[1] - p[0] ** 2), a[0] - p[0], 0.1 * p[0] * p[1]])


_ROSENBROCK_START = jnp.array([-1.2, 1.0])


def test_unrolled_adjoint_runs_the_whole_budget():
    """``max_steps`` means the same for both adjoints: the unrolled loop counts the first
    (linearise-only) trial too, and stopped one step short with status RUNNING (-1)."""
    a = jnp.array([1.0])
    sols = [jo.least_squares(_rosenbrock_residual, _ROSENBROCK_START, a, max_steps=5,
                             adjoint=adjoint) for adjoint in ("implicit", "unrolled")]
    for sol in sols:
        assert int(sol.status) == Results.MAX_STEPS
        assert int(sol.num_steps) == 5
    np.testing.assert_array_equal(sols[0].params, sols[1].params)


def test_vmap_of_unrolled_gradient_of_three_dogleg_steps():
    """The default-tier case of the test below (two compilations): each lane's gradient
    through three unrolled Dogleg steps equals its own."""

    def loss(a):
        return jo.least_squares(_rosenbrock_residual, _ROSENBROCK_START, a,
                                solver=jo.LM(strategy=jo.Dogleg()), adjoint="unrolled",
                                max_steps=3).params.sum()

    batch = jnp.array([[1.0], [1.5]])
    lanes = jax.vmap(jax.grad(loss))(batch)
    single = jax.jit(jax.grad(loss))
    for i in range(2):
        np.testing.assert_allclose(lanes[i], single(batch[i]), rtol=1e-12)


@pytest.mark.slow  # five compilations of the unrolled loop per solver (~10 s)
@pytest.mark.parametrize("solver", [
    jo.LM(strategy=jo.Dogleg()),
    pytest.param(jo.LM(linear_solver=jo.QR()), marks=pytest.mark.slow),
    pytest.param(jo.GN(), marks=pytest.mark.slow),
    pytest.param(jo.GN(linear_solver=jo.QR()), marks=pytest.mark.slow),
    pytest.param(jo.LM(linear_solver=jo.QR(), strategy=jo.Dogleg()), marks=pytest.mark.slow),
], ids=["dogleg", "lm-qr", "gn", "gn-qr", "dogleg-qr"])
def test_vmap_of_unrolled_gradient_equals_each_problems_gradient(solver):
    """vmap(grad) through the unrolled loop raised "a linear solver returned non-finite
    output": JAX stores zero residuals for the lax.cond branch a lane did not take (the
    first trial's skipped solve), and under vmap lineax's transpose solve ran on that zero
    factor and raised. Dogleg's step also had NaN derivatives at g = 0 (plain norms and
    square root). Each lane's gradient now equals its own, which matches the implicit one
    once converged (to 1e-4: with a nonzero residual the iterates' derivatives converge
    linearly and lag the iterates, which stop at the cost tolerance)."""

    def loss(a, steps):
        return jo.least_squares(_rosenbrock_residual, _ROSENBROCK_START, a, solver=solver,
                                adjoint="unrolled", max_steps=steps).params.sum()

    batch = jnp.array([[1.0], [1.5]])
    for steps in (3, 60):
        batched = jax.vmap(jax.grad(loss), (0, None))(batch, steps)
        for i in range(2):
            np.testing.assert_allclose(batched[i], jax.grad(loss)(batch[i], steps),
                                       rtol=1e-12)
    implicit = jax.grad(lambda a: jo.least_squares(
        _rosenbrock_residual, _ROSENBROCK_START, a, solver=solver).params.sum())(batch[1])
    np.testing.assert_allclose(batched[1], implicit, rtol=1e-4)


def test_unrolled_gradient_of_a_batch_with_a_problem_stopped_at_the_start():
    """A batch of two: one problem converges, the other's Jacobian is infinite at its
    start (NON_FINITE after 0 steps). vmap(grad) through the unrolled solver raised
    lineax's "non-finite input" for the whole batch: the loop still computed the stopped
    problem's trials. Each problem now gets its own gradient, as in a loop (vmap audit)."""
    def res(p, a):
        x, y = p[0], p[1]
        return jnp.array([a[0] * (y - x ** 2), a[1] - x, jnp.sqrt(jnp.abs(x) + a[2])])

    a = jnp.array([[10.0, 1.0, 1.0], [1.0, 0.0, 0.0]])
    p = jnp.array([[-1.2, 1.0], [0.0, 0.3]])

    def loss(a, p):
        return jnp.sum(jo.least_squares(res, p, a, max_steps=40, adjoint="unrolled").params ** 2)

    g = jax.grad(loss)
    batched = np.asarray(jax.vmap(g)(a, p))
    looped = np.stack([np.asarray(g(a[i], p[i])) for i in range(2)])
    np.testing.assert_allclose(batched[0], looped[0], rtol=1e-12)
    assert np.all(np.isfinite(batched[0])) and np.abs(batched[0]).max() > 0.1
    np.testing.assert_array_equal(np.isnan(batched[1]), np.isnan(looped[1]))
