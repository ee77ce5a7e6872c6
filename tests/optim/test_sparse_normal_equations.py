"""The coloured path's sparse normal equations: JᵀJ in CSR, solved by sparse Cholesky.

References are independent of the code under test: ``jax.jacfwd`` of the flattened
residual (JᵀJ formed densely), numpy's dense solve, finite differences, and the dense path
(``jacobian="fwd"``: dense JᵀJ and dense Cholesky).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose.optim as jo
from jaxpose.optim._sparse_hessian import SPARSE_MIN_SIZE, SparseHessian
from jaxpose.results import Results

N = 200


def chain(x: jax.Array, y: jax.Array) -> jax.Array:
    """1D smoothing chain: a nonlinear data term per variable and a nonlinear smoothness
    term per neighbour pair (tridiagonal JᵀJ); scalar residual blocks."""
    data = x + 0.2 * jnp.sin(x) - y
    d = x[1:] - x[:-1]
    smooth = 2.0 * d + 0.3 * d**3
    return jnp.concatenate([data, smooth])[:, None]


def chain2(x: jax.Array, y: jax.Array) -> jax.Array:
    """The chain with 2-d residual blocks (data, smoothness) that weights mix."""
    d = x[1:] - x[:-1]
    return jnp.stack([x[1:] + 0.2 * jnp.sin(x[1:]) - y[1:], 2.0 * d + 0.3 * d**3], -1)


def window(x: jax.Array, _: object) -> jax.Array:
    """Each residual block touches 11 consecutive variables: JᵀJ has bandwidth 10 (fill
    about 0.1 at n = 200, above the sparse threshold)."""
    idx = np.arange(x.shape[0] - 10)[:, None] + np.arange(11)[None, :]
    return (jnp.sum(jnp.sin(x[idx]), -1) - 0.5)[:, None]


def _data(n: int = N, seed: int = 0) -> jax.Array:
    return jnp.asarray(np.cumsum(np.random.default_rng(seed).normal(size=n)) * 0.3)


def _jacfwd(fn, x, args) -> np.ndarray:
    return np.asarray(jax.jacfwd(lambda e: fn(e, args).reshape(-1))(x))


# ----------------------------------------------------------------------------------
# assembly
# ----------------------------------------------------------------------------------
def test_csr_normal_matrix_equals_dense_jtj_without_an_n_by_n_array():
    y = _data()
    x = y + 0.1 * jnp.asarray(np.random.default_rng(1).normal(size=N))
    prob = jo.Problem(chain, jacobian="sparse")
    pat = prob.pattern(x, y)
    assert pat.csr is not None and pat.groups is None
    assert pat.csr.nnz == 3 * N - 2  # tridiagonal
    lin = prob.linearize_structured(x, y)
    h = lin.jac.normal()
    assert isinstance(h, SparseHessian)
    assert [leaf.shape for leaf in jax.tree.leaves(h)] == [(3 * N - 2,)]
    j = _jacfwd(chain, x, y)
    np.testing.assert_allclose(np.asarray(h.dense()), j.T @ j, rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(np.asarray(h.diagonal()), np.diag(j.T @ j), rtol=1e-13)
    v = np.random.default_rng(2).normal(size=N)
    np.testing.assert_allclose(np.asarray(h @ jnp.asarray(v)), j.T @ (j @ v), atol=1e-11)
    # the damped solve against numpy's dense solve
    a = np.abs(np.random.default_rng(3).normal(size=N))
    got = h.solve(jnp.asarray(v), jnp.asarray(a))
    want = np.linalg.solve(j.T @ j + np.diag(a), v)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-10, atol=1e-12)


def test_csr_normal_matrix_with_weights_and_kernel_matches_the_dense_linearisation():
    y = _data()
    x = y + 0.2
    w = jnp.asarray(np.random.default_rng(4).normal(size=(N - 1, 2, 2)))
    w = jnp.einsum("bij,bkj->bik", w, w) + jnp.eye(2)
    kw = {"weights": w, "kernel": jo.Huber(0.5), "corrector": jo.Triggs()}
    lin = jo.Problem(chain2, jacobian="sparse", **kw).linearize_structured(x, y)
    h = lin.jac.normal()
    assert isinstance(h, SparseHessian)
    j = np.asarray(jo.Problem(chain2, jacobian="fwd", **kw).linearize(x, y).jac)
    np.testing.assert_allclose(np.asarray(h.dense()), j.T @ j, rtol=1e-12, atol=1e-12)


def test_auto_choice_of_the_hessian_form():
    y = _data()
    mode, pat = jo.Problem(chain).jacobian_mode(jnp.zeros(N), y)
    assert mode == "sparse" and pat.csr is not None
    # small: coloured Jacobian, dense H (a dense Cholesky beats a host call)
    small = SPARSE_MIN_SIZE // 2
    mode, pat = jo.Problem(chain).jacobian_mode(jnp.zeros(small), y[:small])
    assert mode == "sparse" and pat.csr is None and pat.groups is None
    # too full (bandwidth 10 of 200): coloured Jacobian, dense H
    mode, pat = jo.Problem(window).jacobian_mode(jnp.zeros(N), None)
    assert mode == "sparse" and pat.num_colours == 11 and pat.csr is None
    # the dense path never builds one
    assert jo.Problem(chain, jacobian="fwd").jacobian_mode(jnp.zeros(N), y) == ("fwd", None)


# ----------------------------------------------------------------------------------
# solves
# ----------------------------------------------------------------------------------
@pytest.mark.parametrize("solver", [
    jo.LM(), jo.GN(), jo.LM(strategy=jo.Dogleg()),
    jo.LM(linear_solver=jo.CG()),
    # dense fallbacks on the sparse form
    pytest.param(jo.LM(linear_solver=jo.SVD()), marks=pytest.mark.slow),
    pytest.param(jo.LM(linear_solver=jo.QR()), marks=pytest.mark.slow),
    pytest.param(jo.LM(linear_solver=jo.LU()), marks=pytest.mark.slow),
], ids=["LM", "GN", "Dogleg", "CG", "SVD", "QR", "LU"])
def test_chain_solution_equals_dense_path(solver):
    y = _data()
    x0 = jnp.zeros(N)
    sols = [jo.least_squares(chain, x0, y, solver, jacobian=m) for m in ("sparse", "fwd")]
    assert int(sols[0].status) == int(sols[1].status) == Results.CONVERGED
    assert int(sols[0].num_steps) == int(sols[1].num_steps)
    np.testing.assert_allclose(sols[0].params, sols[1].params, rtol=0, atol=1e-10)
    np.testing.assert_allclose(float(sols[0].cost), float(sols[1].cost), rtol=1e-10)


def test_singular_gauss_newton_system_reports_non_finite_like_the_dense_path():
    # the last variable enters no residual: H is singular, so Cholesky fails (NaN step)
    def res(x, y):
        return chain(x[:-1], y[:-1])

    y, x0 = _data(N + 1), jnp.zeros(N + 1)
    assert jo.Problem(res).pattern(x0, y).csr is not None
    sols = [jo.least_squares(res, x0, y, jo.GN(), jacobian=m) for m in ("sparse", "fwd")]
    assert int(sols[0].status) == int(sols[1].status) == Results.NON_FINITE
    np.testing.assert_array_equal(sols[0].params, x0)
    # LM's diagonal lift makes it well posed on both paths
    sols = [jo.least_squares(res, x0, y, jacobian=m) for m in ("sparse", "fwd")]
    np.testing.assert_allclose(sols[0].params, sols[1].params, atol=1e-10)


def test_vmap_keeps_per_problem_results():
    ys = jnp.stack([_data(seed=s) for s in (5, 6, 7)]) * jnp.asarray([[1.0], [3.0], [-0.5]])
    x0 = jnp.zeros(N)
    sols = jax.jit(jax.vmap(lambda y: jo.least_squares(chain, x0, y, jacobian="sparse")))(ys)
    for k in range(3):
        ref = jo.least_squares(chain, x0, ys[k], jacobian="fwd")
        assert int(sols.num_steps[k]) == int(ref.num_steps)
        np.testing.assert_allclose(sols.params[k], ref.params, atol=1e-10)
    assert len(set(np.asarray(sols.num_steps).tolist())) > 1  # they did not share a loop


def test_repeated_calls_do_not_retrace():
    traces = []

    def counted(x, y):
        traces.append(1)  # runs only while tracing
        return chain(x, y)

    y, x0 = _data(), jnp.zeros(N)
    assert jo.Problem(counted).pattern(x0, y).csr is not None
    first = jo.least_squares(counted, x0, y)
    n = len(traces)
    again = jo.least_squares(counted, x0 + 0.1, y * 1.0)
    assert len(traces) == n
    np.testing.assert_allclose(again.params, first.params, atol=1e-6)


def test_grad_through_the_implicit_adjoint_matches_dense_and_finite_differences():
    x0, y = jnp.zeros(N), _data()
    wts = jnp.linspace(0.5, 1.5, N)

    def loss(y, mode, adjoint="implicit"):
        sol = jo.least_squares(chain, x0, y, jacobian=mode, adjoint=adjoint, cost_rtol=0.0,
                               gtol=1e-12)
        return jnp.sum(wts * sol.params**2)

    g_sparse = jax.jit(jax.grad(lambda y: loss(y, "sparse")))(y)
    g_dense = jax.grad(lambda y: loss(y, "fwd"))(y)
    np.testing.assert_allclose(g_sparse, g_dense, rtol=1e-9, atol=1e-12)
    d = jnp.asarray(np.random.default_rng(8).normal(size=N))
    eps = 1e-4  # the solves stop at ‖δ‖ ≤ 1e-10: a smaller step is in their noise
    fd = (loss(y + eps * d, "sparse") - loss(y - eps * d, "sparse")) / (2 * eps)
    np.testing.assert_allclose(float(g_sparse @ d), float(fd), rtol=1e-6)
    # per problem under vmap
    gv = jax.vmap(jax.grad(lambda y: loss(y, "sparse")))(jnp.stack([y, 2.0 * y]))
    np.testing.assert_allclose(gv[0], g_dense, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(gv[1], jax.grad(lambda y: loss(y, "fwd"))(2.0 * y), rtol=1e-9,
                               atol=1e-12)


@pytest.mark.slow
def test_grad_through_the_unrolled_iterations_matches_dense():
    x0, y = jnp.zeros(N), _data()

    def loss(y, mode):
        sol = jo.least_squares(chain, x0, y, jacobian=mode, adjoint="unrolled", max_steps=20)
        return jnp.sum(sol.params**2)

    np.testing.assert_allclose(jax.grad(lambda y: loss(y, "sparse"))(y),
                               jax.grad(lambda y: loss(y, "fwd"))(y), rtol=1e-9, atol=1e-12)


def test_float32_sparse_solve():
    y = _data()
    x0 = jnp.zeros(N, jnp.float32)
    sol = jo.least_squares(chain, x0, y.astype(jnp.float32), jacobian="sparse", gtol=1e-5)
    assert sol.params.dtype == jnp.float32
    assert int(sol.status) == Results.CONVERGED
    ref = jo.least_squares(chain, jnp.zeros(N), y, jacobian="fwd")
    np.testing.assert_allclose(np.asarray(sol.params), np.asarray(ref.params), atol=1e-4)


def test_gauss_newton_implicit_adjoint_solves_backwards_on_the_sparse_form():
    x0, y = jnp.zeros(N), _data()
    adjoint = jo.ImplicitAdjoint(linear_solver=jo.Cholesky(), hessian="gauss_newton")

    def loss(y, mode):
        sol = jo.least_squares(chain, x0, y, jacobian=mode, adjoint=adjoint)
        return jnp.sum(sol.params**2)

    jaxpr = str(jax.make_jaxpr(jax.grad(lambda y: loss(y, "sparse")))(y))
    assert "custom_linear_solve" in jaxpr and "pure_callback" in jaxpr
    np.testing.assert_allclose(jax.jit(jax.grad(lambda y: loss(y, "sparse")))(y),
                               jax.grad(lambda y: loss(y, "fwd"))(y), rtol=1e-9, atol=1e-12)
