"""Linear solvers vs dense numpy solves; damping; singular systems never crash."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose.optim as jo

SOLVERS = [jo.Cholesky(), jo.LU(), jo.QR(), jo.SVD(), jo.CG(rtol=1e-13, atol=0.0)]


def _problem(seed, m=12, n=5, dtype=np.float64):
    rng = np.random.default_rng(seed)
    j = rng.normal(size=(m, n)).astype(dtype)
    r = rng.normal(size=m).astype(dtype)
    return j, r, j.T @ j, j.T @ r


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__)
def test_damped_solution_matches_numpy(solver):
    j, r, h, g = _problem(0)
    a = np.linspace(0.1, 2.0, 5)
    got = solver.solve(jnp.asarray(j), jnp.asarray(r), jnp.asarray(h), jnp.asarray(g),
                       jnp.asarray(a))
    want = np.linalg.solve(h + np.diag(a), -g)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    # undamped: the least-squares solution of J δ ≈ -r
    got0 = solver.solve(jnp.asarray(j), jnp.asarray(r), jnp.asarray(h), jnp.asarray(g),
                        jnp.zeros(5))
    np.testing.assert_allclose(got0, np.linalg.lstsq(j, -r, rcond=None)[0], rtol=1e-8)


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__)
def test_float32(solver):
    j, r, h, g = _problem(1, dtype=np.float32)
    got = solver.solve(jnp.asarray(j), jnp.asarray(r), jnp.asarray(h), jnp.asarray(g),
                       jnp.full(5, 0.5, jnp.float32))
    assert got.dtype == jnp.float32
    want = np.linalg.solve((h + 0.5 * np.eye(5)).astype(np.float64), -g.astype(np.float64))
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-5)


def test_rank_deficient_systems():
    j, r, _, _ = _problem(2, n=4)
    j = np.concatenate([j, j[:, :1]], 1)  # duplicated column: JᵀJ singular
    h, g = j.T @ j, j.T @ r
    args = (jnp.asarray(j), jnp.asarray(r), jnp.asarray(h), jnp.asarray(g))
    # SVD: the minimum-norm least-squares step (pseudo-inverse)
    np.testing.assert_allclose(jo.SVD().solve(*args, jnp.zeros(5)),
                               -np.linalg.pinv(j) @ r, rtol=1e-8, atol=1e-10)
    # Cholesky / LU / QR (not rank revealing): no exception undamped; any damping makes
    # the system well posed (LM's path)
    for solver in (jo.Cholesky(), jo.LU(), jo.QR()):
        solver.solve(*args, jnp.zeros(5))  # may be non-finite, must not raise
        damped = solver.solve(*args, jnp.full(5, 1e-3))
        np.testing.assert_allclose(damped, np.linalg.solve(h + 1e-3 * np.eye(5), -g),
                                   rtol=1e-7)


def test_solvers_pass_through_jit_as_arguments():
    """A solver object is a jit argument like any pytree: its tolerances are static, so
    lineax sees Python floats (CG's rtol/atol once came in as tracers and failed)."""
    import jax

    from .problems import EXP_ARGS, EXP_OPT, exp_residual

    run = jax.jit(lambda s, x: jo.least_squares(exp_residual, x, EXP_ARGS, solver=s).params)
    for ls in (jo.CG(rtol=1e-12), jo.SVD(rcond=1e-12)):
        got = run(jo.LM(linear_solver=ls), jnp.array([1.0, 1.0]))
        np.testing.assert_allclose(np.asarray(got), EXP_OPT, rtol=1e-6)
