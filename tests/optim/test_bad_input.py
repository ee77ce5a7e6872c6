"""Bad input: NaN at the start / mid-run, malformed weights and options, singular systems."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose as jp
import jaxpose.optim as jo

from .test_least_squares import run_steps


def _lin(x, args):
    a, b = args
    return (a @ x - b)[:, None]


def _singular_args():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(10, 3))
    a = np.concatenate([a, a[:, :1]], 1)  # duplicated column: AᵀA singular
    b = rng.normal(size=10)
    return a, b


def test_nan_residual_at_start_raises_naming_residual_fn():
    def bad(x, args):
        return jnp.log(x - 1.0)  # NaN at x = 0

    with pytest.raises(Exception, match="residual_fn"):
        jax.block_until_ready(jo.least_squares(bad, jnp.zeros(2)))
    # the check lives on every output a caller may keep alone (XLA drops unused checks)
    for out in ("params", "cost", "initial_cost"):
        with pytest.raises(Exception, match="residual_fn"):
            jax.block_until_ready(  # an accelerator raises when the result is read
                jax.jit(lambda x, out=out: getattr(jo.least_squares(bad, x), out))(jnp.zeros(2)))


def test_nan_mid_run_reports_non_finite_and_keeps_best():
    # Gauss-Newton on x² − 4 from x = 10 visits 5.2, 3.08, then 2.19 where the residual is
    # NaN (domain x > 2.5): status NON_FINITE, the best finite estimate (3.08) is kept
    def res(x, args):
        return jnp.where(x > 2.5, x * x - 4.0, jnp.nan)

    state = run_steps(jo.GN(), res, jnp.array([10.0]), None)
    assert int(state.status) == jp.Results.NON_FINITE
    assert int(state.num_accepted) == 2
    x1 = 10.0 - 96.0 / 20.0
    x2 = x1 - (x1 * x1 - 4.0) / (2 * x1)
    np.testing.assert_allclose(state.best_params, [x2], rtol=1e-12)
    assert float(state.best_cost) == pytest.approx(0.5 * (x2 * x2 - 4.0) ** 2)
    # LM: every trial away from the start is NaN -> rejected with growing damping until the
    # damping bound, then NON_FINITE with the initial params kept
    def res2(x, args):
        return jnp.where(x == 1.0, x - 3.0, jnp.nan)

    sol = jo.least_squares(res2, jnp.array([1.0]))
    assert int(sol.status) == jp.Results.NON_FINITE
    np.testing.assert_array_equal(sol.params, [1.0])
    assert int(sol.num_accepted) == 0 and float(sol.cost) == pytest.approx(2.0)


def test_singular_normal_equations_do_not_crash():
    a, b = _singular_args()
    args = (jnp.asarray(a), jnp.asarray(b))
    lstsq_res = a @ np.linalg.pinv(a) @ b - b
    # damped path (LM + Cholesky): a least-squares minimiser
    lm = run_steps(jo.LM(), _lin, jnp.zeros(4), args)
    assert int(lm.status) == jp.Results.CONVERGED
    np.testing.assert_allclose(a @ np.asarray(lm.best_params) - b, lstsq_res, atol=1e-8)
    # pseudo-inverse path (GN + SVD): exactly the minimum-norm solution
    gn = run_steps(jo.GN(jo.SVD()), _lin, jnp.zeros(4), args)
    assert int(gn.status) == jp.Results.CONVERGED
    np.testing.assert_allclose(gn.best_params, np.linalg.pinv(a) @ b, rtol=1e-9, atol=1e-12)
    # undamped Cholesky: no exception, a status, the initial estimate kept
    bad = run_steps(jo.GN(jo.Cholesky()), _lin, jnp.zeros(4), args)
    assert int(bad.status) == jp.Results.NON_FINITE
    np.testing.assert_array_equal(bad.best_params, np.zeros(4))


def test_mismatched_weights_raise_naming_weights():
    x0 = jnp.zeros(2)

    def res(x, args):
        return jnp.stack([x, 2 * x])  # (2, 2): two blocks of dimension 2

    for w in (jnp.eye(3), jnp.ones((3, 2, 2)), jnp.ones((2,)), jnp.ones((2, 3, 3))):
        with pytest.raises(ValueError, match="weights"):
            jo.least_squares(res, x0, weights=w)
    with pytest.raises(ValueError, match="weights"):
        jo.least_squares(res, x0, weights={"a": jnp.eye(2)})
    # a non-positive-definite information matrix is caught at run time
    with pytest.raises(Exception, match="weights"):
        jax.block_until_ready(jo.least_squares(res, x0, weights=-jnp.eye(2)))


def test_bad_options_raise_clear_errors():
    x0 = jnp.zeros(2)

    def res(x, args):
        return x - 1.0

    with pytest.raises(ValueError, match="adjoint"):
        jo.least_squares(res, x0, adjoint="backprop")
    with pytest.raises(ValueError, match="jacobian"):
        jo.least_squares(res, x0, jacobian="central")
    with pytest.raises(ValueError, match="jacobian"):
        jo.least_squares(res, x0, jacobian=lambda x, a: jnp.eye(3))
    with pytest.raises(TypeError, match="solver"):
        jo.least_squares(res, x0, solver=jo.TrustRegion())
    with pytest.raises(ValueError, match="max_steps"):
        jo.least_squares(res, x0, max_steps=-1)
    with pytest.raises(ValueError, match="kernel"):
        jo.least_squares(res, x0, kernel={"a": jo.Huber()})
    with pytest.raises(TypeError, match="residual_fn"):
        jo.least_squares(lambda x, a: jnp.arange(2), x0)
    with pytest.raises(TypeError, match="residual_fn"):
        jo.least_squares("not callable", x0)
    with pytest.raises(TypeError, match="strategy"):
        jo.LM(strategy=jo.Cholesky())


def test_nonfinite_jacobian_at_start_reports_status_not_exception():
    """The docstring promised a RuntimeError for a non-finite Jacobian at the start; code and
    docstring now agree on a status (solvers report a status, as the graph solver does):
    sqrt(x) + 1 at x = 0 has a finite residual and an infinite Jacobian → NON_FINITE at
    once, initial params kept. A non-finite *residual* at the start still raises."""

    def res(x, args):
        return jnp.sqrt(x) + 1.0

    for run in (jo.least_squares, jax.jit(jo.least_squares, static_argnums=0)):
        sol = run(res, jnp.zeros(2))
        assert int(sol.status) == jp.Results.NON_FINITE
        np.testing.assert_array_equal(sol.params, np.zeros(2))
        assert int(sol.num_steps) == 0 and float(sol.cost) == pytest.approx(1.0)
    assert "RuntimeError" in jo.least_squares.__doc__ and "sqrt(x)" in jo.least_squares.__doc__


@pytest.mark.parametrize("keep", ["status", "num_steps", "grad_norm", "params"])
def test_nonfinite_residual_at_start_raises_under_jit_whatever_is_kept(keep):
    """docs/least-squares.md: a NaN/Inf residual at the initial params raises, also under
    jit. The check was attached to params and costs only, so a caller keeping the status
    (as the vmap example does) got NON_FINITE and no error."""
    def run(a):
        return getattr(jo.least_squares(lambda p, a: p - a + jnp.nan, jnp.zeros(3), a), keep)

    with pytest.raises(Exception, match="returned NaN/Inf at the initial params"):
        jax.block_until_ready(jax.jit(run)(jnp.ones(3)))


@pytest.mark.parametrize("max_steps", [3, 10])
def test_all_nan_trials_end_non_finite_within_a_small_budget(max_steps):
    """Every trial NaN and max_steps < max_rejects: NON_FINITE (was MAX_STEPS)."""

    def res(x, args):
        return jnp.where(x == 1.0, x - 3.0, jnp.nan)

    for solver in (jo.LM(), jo.LM(strategy=jo.Adaptive())):
        sol = jo.least_squares(res, jnp.array([1.0]), solver=solver, max_steps=max_steps)
        assert int(sol.status) == jp.Results.NON_FINITE
        np.testing.assert_array_equal(sol.params, [1.0])
    # finite trials that run out of budget are still MAX_STEPS
    sol = jo.least_squares(
        lambda x, a: jnp.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]]),
        jnp.array([-1.2, 1.0]),
        max_steps=2,
    )
    assert int(sol.status) == jp.Results.MAX_STEPS


# Found by an audit (session 48): options that switched a test off, or a zero step read as
# convergence
def _rosenbrock(p, _):
    return jnp.array([p[0] - 1.0, 10 * (p[1] - p[0] ** 2)])


def test_zero_budget_reports_max_steps_and_the_gradient_at_the_start():
    """max_steps=0 gave status RUNNING (-1) and grad_norm 0 from a placeholder system;
    graph.solve gives MAX_STEPS. At (-1.2, 1): g = Jᵀr = (-107.8, -44) by hand."""
    x0 = jnp.array([-1.2, 1.0])
    sol = jo.least_squares(_rosenbrock, x0, max_steps=0)
    assert sol.status_name == "max_steps" and int(sol.num_steps) == 0
    np.testing.assert_allclose(float(sol.grad_norm), 107.8, rtol=1e-12)
    np.testing.assert_allclose(float(sol.cost), 0.5 * (2.2**2 + 4.4**2), rtol=1e-12)
    np.testing.assert_array_equal(sol.params, x0)


@pytest.mark.parametrize("make, match", [
    (lambda: jo.Stopping(gtol=float("nan")), r"gtol=nan: expected a non-negative"),
    (lambda: jo.Stopping(xtol=-1e-3), r"xtol=-0.001: expected a non-negative"),
    (lambda: jo.StopOnPlateau(steps=50, decreasing=float("nan")), r"decreasing\)=nan"),
    (lambda: jo.CG(rtol=float("nan")), r"CG\(rtol\)=nan"),
    (lambda: jo.CG(atol=-1.0), r"CG\(atol\)=-1.0"),
    (lambda: jo.CG(max_steps=0), r"CG\(max_steps\): expected an int >= 1, got 0"),
    (lambda: jo.SVD(rcond=float("nan")), r"SVD\(rcond\)=nan: expected None or a float in"),
    (lambda: jo.SVD(rcond=1.0), r"SVD\(rcond\)=1.0"),
    (lambda: jo.LevenbergMarquardt(accept_ratio=1.5), r"0 ≤ accept_ratio < 1"),
    (lambda: jo.LevenbergMarquardt(diag_min=1.0, diag_max=0.1), r"0 ≤ diag_min ≤ diag_max"),
    (lambda: jo.LevenbergMarquardt(diag_min=float("nan")), r"diag_min=nan"),
])
def test_options_that_would_fake_convergence_are_refused(make, match):
    """Each gave a zero step (or switched a test off), read as CONVERGED at the start
    point of Rosenbrock's problem (cost 12.1 against the optimum 0) or DIVERGED there."""
    with pytest.raises(ValueError, match=match):
        make()


def test_covariance_rcond_is_checked_and_only_for_svd():
    """rcond=nan dropped every eigenvalue (an all-zero covariance); with method='cholesky'
    it was silently ignored."""
    a, b = _singular_args()
    a = a[:, :3]  # full rank
    x = jnp.asarray(np.linalg.lstsq(a, b, rcond=None)[0])
    with pytest.raises(ValueError, match=r"covariance\(rcond\)=nan"):
        jo.covariance(_lin, x, (a, b), method="svd", rcond=float("nan"))
    with pytest.raises(ValueError, match=r"only method='svd' drops small eigenvalues"):
        jo.covariance(_lin, x, (a, b), rcond=1e-8)
    np.testing.assert_allclose(jo.covariance(_lin, x, (a, b), method="svd", rcond=1e-8),
                               np.linalg.inv(a.T @ a), rtol=1e-10)


def test_a_kernel_parameter_put_in_after_construction_is_checked():
    """Huber(-1.0) is refused when made, but a Python float put in with eqx.tree_at stayed
    static under jit and was never checked: least_squares and graph.solve returned a
    negative cost (−10.5) with status diverged."""
    import equinox as eqx

    from jaxpose import graph as G

    bad = eqx.tree_at(lambda k: k.delta, jo.Huber(1.0), -1.0)
    a = jnp.array([0.0, 0.5, 10.0])
    with pytest.raises(ValueError, match=r"Huber\(delta=-1.0\): delta has to be positive"):
        jo.least_squares(lambda x, a: (x - a)[:, None], jnp.zeros(3), a, kernel=bad)
    graph = G.FactorGraph([G.Factor(lambda x, z: x - z, [("x", np.arange(3))],
                                    data=a[:, None], kernel=bad)], {"x": jnp.zeros((3, 1))})
    with pytest.raises(ValueError, match=r"Huber\(delta=-1.0\): delta has to be positive"):
        G.solve(graph)
