"""jaxpose._small_linalg: written-out Cholesky, solve and inverse of small batched matrices.

References are NumPy's LAPACK results (values) and ``jnp.linalg`` (derivatives: the same
functions, differentiated by JAX's own rules). The regression this module exists for —
jaxlib 0.10.2's batched LAPACK calls deadlocking XLA:CPU's thread pool when a program runs
as many of them at once as the pool has threads — shows as a hang, not a failure, so the
last tests check the cause instead: the programs of jaxpose's batched small-block paths
contain no LAPACK custom call.
"""

from __future__ import annotations

import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose import _small_linalg as sl

jax.config.update("jax_enable_x64", True)

SIZES = list(range(1, sl.UNROLL_MAX + 1))


def _spd(rng, batch, d):
    a = rng.normal(size=(batch, d, d))
    return a @ np.swapaxes(a, 1, 2) + 0.5 * np.eye(d)


def _general(rng, batch, d):
    # well conditioned, rows out of order (a pivoted LU would permute them)
    a = rng.normal(size=(batch, d, d)) + 2.0 * np.eye(d)
    return a[:, rng.permutation(d)]


@pytest.mark.parametrize("d", SIZES)
def test_spd_values_equal_lapack_float64(d):
    spd = _spd(np.random.default_rng(d), 40, d)
    np.testing.assert_allclose(jax.jit(sl.cholesky)(spd), np.linalg.cholesky(spd),
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(jax.jit(sl.spd_inv)(spd), np.linalg.inv(spd),
                               rtol=1e-10, atol=1e-11)


@pytest.mark.parametrize("d", [1, 2, 3, 4])
def test_general_values_equal_lapack_float64(d):
    rng = np.random.default_rng(d)
    a, b = _general(rng, 40, d), rng.normal(size=(40, d, 3))
    np.testing.assert_allclose(jax.jit(sl.solve)(a, b), np.linalg.solve(a, b),
                               rtol=1e-10, atol=1e-11)
    np.testing.assert_allclose(jax.jit(sl.inv)(a), np.linalg.inv(a), rtol=1e-10, atol=1e-11)


@pytest.mark.parametrize("d", [2, 3, 6])
def test_values_float32(d):
    rng = np.random.default_rng(10 + d)
    spd, a = _spd(rng, 20, d), _general(rng, 20, min(d, 3))
    b = rng.normal(size=(20, min(d, 3), 2))
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    chol, inv, x = sl.cholesky(f32(spd)), sl.spd_inv(f32(spd)), sl.solve(f32(a), f32(b))
    assert chol.dtype == inv.dtype == x.dtype == jnp.float32
    np.testing.assert_allclose(chol, np.linalg.cholesky(spd), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(inv, np.linalg.inv(spd), rtol=2e-3, atol=1e-4)
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-3, atol=1e-4)


def test_spd_functions_use_the_symmetric_part_and_flag_non_pd_with_nan():
    rng = np.random.default_rng(0)
    spd = _spd(rng, 3, 4)
    x = rng.normal(size=(3, 4, 4))
    skewed = spd + x - np.swapaxes(x, 1, 2)  # its symmetric part is spd
    np.testing.assert_allclose(sl.cholesky(skewed), np.linalg.cholesky(spd), rtol=1e-12)
    np.testing.assert_allclose(sl.spd_inv(skewed), np.linalg.inv(spd), rtol=1e-10)
    bad = spd.copy()
    bad[1] = -bad[1]  # negative definite: only its results are NaN, the others exact
    for fn, ref in ((sl.cholesky, np.linalg.cholesky), (sl.spd_inv, np.linalg.inv)):
        out = np.asarray(fn(bad))
        assert np.isnan(out[1]).all()
        np.testing.assert_allclose(out[[0, 2]], ref(spd[[0, 2]]), rtol=1e-10)
        assert np.isnan(np.asarray(fn(np.full((2, 2), np.nan)))).all()


@pytest.mark.parametrize("d", [2, 3])
def test_singular_matrices_give_non_finite_solutions(d):
    a = np.ones((d, d))
    assert not np.isfinite(np.asarray(sl.solve(a, np.ones((d, 1))))).all()
    assert not np.isfinite(np.asarray(sl.inv(a))).all()


@pytest.mark.parametrize("d", [2, 3, 4])
def test_derivatives_equal_jnp_linalg_to_second_order(d):
    rng = np.random.default_rng(20 + d)
    spd = jnp.asarray(_spd(rng, 1, d)[0])
    w = jnp.asarray(rng.normal(size=(d, d)))

    def pair(fn_small, fn_ref, x):
        ours = lambda m: jnp.sum(w[:, : fn_small(m).shape[-1]] * jnp.sin(fn_small(m)))  # noqa: E731
        ref = lambda m: jnp.sum(w[:, : fn_ref(m).shape[-1]] * jnp.sin(fn_ref(m)))  # noqa: E731
        direction = jnp.asarray(rng.normal(size=x.shape))

        @functools.partial(jax.jit, static_argnums=0)
        def derivatives(f, x):  # grad, hessian (reverse over forward), forward over reverse
            return (jax.grad(f)(x), jax.hessian(f)(x),
                    jax.jvp(jax.grad(f), (x,), (direction,))[1])

        for got, want in zip(derivatives(ours, x), derivatives(ref, x), strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-10)

    sym = lambda m: 0.5 * (m + m.T)  # noqa: E731
    pair(sl.cholesky, jnp.linalg.cholesky, spd)
    pair(sl.spd_inv, lambda m: jnp.linalg.inv(sym(m)), spd)
    if d <= 3:
        a, b = jnp.asarray(_general(rng, 1, d)[0]), jnp.asarray(rng.normal(size=(d, 2)))
        pair(lambda m: sl.solve(m, b), lambda m: jnp.linalg.solve(m, b), a)
        pair(sl.inv, jnp.linalg.inv, a)


def test_vmap_and_broadcast_rhs():
    rng = np.random.default_rng(3)
    a, spd = _general(rng, 6, 3), _spd(rng, 6, 5)
    b = rng.normal(size=(3, 2))  # one right-hand side for every matrix
    np.testing.assert_allclose(sl.solve(a, b), np.linalg.solve(a, b), rtol=1e-10)
    np.testing.assert_allclose(jax.vmap(sl.inv)(a), np.linalg.inv(a), rtol=1e-10)
    np.testing.assert_allclose(jax.vmap(sl.spd_inv)(spd), np.linalg.inv(spd), rtol=1e-10)


def test_larger_matrices_fall_back_to_jnp_linalg():
    d = sl.UNROLL_MAX + 1
    spd = _spd(np.random.default_rng(4), 2, d)
    np.testing.assert_allclose(sl.cholesky(spd), np.linalg.cholesky(spd), rtol=1e-12)
    np.testing.assert_allclose(sl.spd_inv(spd), np.linalg.inv(spd), rtol=1e-10)
    if jax.default_backend() == "cpu":  # the fallback is LAPACK's, as documented
        assert "lapack" in jax.jit(sl.cholesky).lower(spd).as_text()


# ---------------------------------------------------------------------------------------
# The batched small-block paths compile without LAPACK calls (which can deadlock XLA:CPU)


def _custom_calls(fun, *args, compiled: bool = False) -> str:
    """The LAPACK custom calls in ``jit(fun)``'s program, sorted: each kind once from the
    lowered program (which shares one function per kind), each call from the ``compiled``
    one (slower to get)."""
    lowered = jax.jit(fun).lower(*args)
    if compiled:
        return " ".join(sorted(re.findall(r'custom_call_target="(lapack_\w+)"',
                                          lowered.compile().as_text())))
    return " ".join(sorted(set(re.findall(r"custom_call @(lapack_\w+)", lowered.as_text()))))


def test_sim3_log_and_jacobians_have_no_lapack_calls():
    from jaxpose.lie import Sim3

    xi = jnp.asarray(np.random.default_rng(5).normal(size=(100, 7)))
    assert _custom_calls(lambda a: Sim3._jl_inv(a), xi) == ""
    assert _custom_calls(lambda a: Sim3.exp(a).log(), xi) == ""
    third = jax.jacfwd(jax.jacrev(lambda a: jnp.sum(jnp.sin(Sim3._jl_inv(a)))))
    assert _custom_calls(jax.vmap(third), xi) == ""


def test_graph_block_paths_have_no_lapack_calls():
    from jaxpose.graph._factor import _traced_sqrt_information
    from jaxpose.graph._linear import block_jacobi

    rng = np.random.default_rng(6)
    info = jnp.asarray(_spd(rng, 500, 6))
    assert _custom_calls(lambda m: _traced_sqrt_information(m, 500), info) == ""
    blocks = (jnp.asarray(_spd(rng, 300, 6)), jnp.asarray(_spd(rng, 200, 3)))
    v = jnp.asarray(rng.normal(size=300 * 6 + 200 * 3))
    assert _custom_calls(lambda b, x: block_jacobi(b)(x), blocks, v) == ""


def test_least_squares_matrix_weights_add_no_lapack_calls():
    from jaxpose.optim import least_squares

    rng = np.random.default_rng(7)
    w = jnp.asarray(_spd(rng, 1, 3)[0])
    target = jnp.asarray(rng.normal(size=(50, 3)))

    def fit(x0, weights):
        return least_squares(lambda x, _: x - target, x0, weights=weights, max_steps=3).params

    # the (traced) weight's per-residual factors are written out; the dense step's own
    # factorisation is the same with and without weights
    without = _custom_calls(lambda x0: fit(x0, None), jnp.zeros((50, 3)), compiled=True)
    assert _custom_calls(fit, jnp.zeros((50, 3)), w, compiled=True) == without


def test_schur_elimination_inverts_point_blocks_without_lapack():
    from jaxpose import graph as jg
    from jaxpose.datasets import synthetic_bal
    from jaxpose.optim import Stopping

    problem = jg.bundle_adjustment_problem(synthetic_bal(5, 40, seed=0)[0], fixed_cameras=[0, 1])
    calls = _custom_calls(
        lambda s: s * jg.solve(problem, linear_solver="schur",
                               stopping=Stopping(max_steps=2)).cost, 1.0)
    assert "getrf" not in calls, calls


def test_imu_information_has_one_lapack_call_at_most():
    # its batched eigvalsh (the singularity check) and a batched LAPACK inverse side by
    # side hung XLA:CPU on 2 cores (5000 windows): the inverse is written out
    from jaxpose.imu import preintegrate

    rng = np.random.default_rng(8)
    pre = preintegrate(rng.normal(size=(50, 10, 3)) * 0.1, rng.normal(size=(50, 10, 3)), 0.01,
                       gyro_noise=1e-3, acc_noise=1e-2)
    calls = _custom_calls(lambda p: p.information, pre)
    assert "getrf" not in calls and "potrf" not in calls, calls
    info = np.asarray(pre.information)
    np.testing.assert_allclose(info, np.linalg.inv(np.asarray(pre.cov)), rtol=1e-8)
