"""Correctors: the corrected block reproduces the exact robust gradient and Hessian."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose.optim as jo

KERNELS = [jo.Huber(0.5), jo.Cauchy(1.0), jo.PseudoHuber(0.8), jo.GemanMcClure(1.2),
           jo.Welsch(1.0), jo.Tukey(2.0), jo.Arctan(0.7), jo.SoftLOne(1.0)]


def _linear_block(seed, nb=7, d=3, n=4, scale=1.0):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(nb, d, n))
    b = scale * rng.normal(size=(nb, d))
    return jnp.asarray(a), jnp.asarray(b)


def _robust_cost(kernel, a, b):
    # independent cost: 0.5 Σ ρ(‖A_i x + b_i‖²), differentiated by JAX
    def f(x):
        r = jnp.einsum("bdn,n->bd", a, x) + b
        return 0.5 * jnp.sum(kernel(jnp.sum(r * r, -1)))
    return f


@functools.cache
def _evaluated():
    """Corrected gradients/Hessians next to autodiff of the robust cost, for every kernel,
    from one compilation."""
    fast_a, fast_b = _linear_block(0, scale=1.5)
    tr_a, tr_b = _linear_block(1, scale=0.15)

    def one(kernel):
        x = jnp.zeros(fast_a.shape[-1])
        e, j = jo.FastTriggs()(kernel, fast_b, fast_a)  # at x = 0: residual b, Jacobian a
        w = kernel.derivative(jnp.sum(fast_b * fast_b, -1))
        fast = {"g": jnp.einsum("bdn,bd->n", j, e), "h": jnp.einsum("bdn,bdm->nm", j, j),
                "g_ref": jax.grad(_robust_cost(kernel, fast_a, fast_b))(x),
                "h_ref": jnp.einsum("b,bdn,bdm->nm", w, fast_a, fast_a)}
        s = jnp.sum(tr_b * tr_b, -1)
        e, j = jo.Triggs()(kernel, tr_b, tr_a)
        f = _robust_cost(kernel, tr_a, tr_b)
        triggs = {"g": jnp.einsum("bdn,bd->n", j, e), "h": jnp.einsum("bdn,bdm->nm", j, j),
                  "g_ref": jax.grad(f)(x), "h_ref": jax.hessian(f)(x),
                  "min_d": jnp.min(1 + 2 * s * kernel.second_derivative(s)
                                   / kernel.derivative(s))}
        return fast, triggs

    run = jax.jit(lambda: {type(k).__name__: one(k) for k in KERNELS})
    return jax.tree.map(np.asarray, run())


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: type(k).__name__)
def test_fast_triggs_gradient_exact_hessian_reweighted(kernel):
    out = _evaluated()[type(kernel).__name__][0]
    np.testing.assert_allclose(out["g"], out["g_ref"], rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(out["h"], out["h_ref"], rtol=1e-11)


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: type(k).__name__)
def test_triggs_matches_exact_hessian_where_defined(kernel):
    # small residuals: 1 + 2 s ρ''/ρ' stays above min_d, so J̃ᵀJ̃ is the exact Hessian of
    # 0.5 ρ(‖A x + b‖²) for a linear residual and J̃ᵀẽ the exact gradient
    out = _evaluated()[type(kernel).__name__][1]
    assert float(out["min_d"]) > 0.05
    np.testing.assert_allclose(out["g"], out["g_ref"], rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(out["h"], out["h_ref"], rtol=1e-9, atol=1e-12)


def test_triggs_clamps_indefinite_curvature():
    kernel = jo.Cauchy(1.0)  # D = (1 - s)/(1 + s) < 0 for s > 1
    a, b = _linear_block(2, nb=5, scale=3.0)
    s = jnp.sum(b * b, -1)
    assert float(jnp.max(s)) > 1.0
    e, j = jo.Triggs(min_d=0.1)(kernel, b, a)
    # the gradient stays exact even where the curvature is clamped
    f = _robust_cost(kernel, a, b)
    x = jnp.zeros(a.shape[-1])
    np.testing.assert_allclose(jnp.einsum("bdn,bd->n", j, e), jax.grad(f)(x), rtol=1e-10)
    # per block, curvature along ê equals ρ'·max(D, min_d); orthogonal directions ρ'
    jb = j[0]
    eb = b[0] / jnp.linalg.norm(b[0])
    d1 = kernel.derivative(s[0])
    big_d = max(float(1 + 2 * s[0] * kernel.second_derivative(s[0]) / d1), 0.1)
    proj = eb @ jb  # ê ᵀ J̃ = √ρ' (1 - α) êᵀ J
    np.testing.assert_allclose(proj, jnp.sqrt(d1 * big_d) * (eb @ a[0]), rtol=1e-10)
    assert bool(jnp.all(jnp.isfinite(e))) and bool(jnp.all(jnp.isfinite(j)))


def test_triggs_ceres_mode_and_zero_residual():
    kernel = jo.Huber(1.0)
    a, b = _linear_block(3, nb=4)
    b = b.at[0].set(0.0)  # a zero residual block must not divide by zero
    e, j = jo.Triggs(negative_curvature=False)(kernel, b, a)
    e_f, j_f = jo.FastTriggs()(kernel, b, a)
    # Huber has ρ'' ≤ 0 everywhere, so Ceres' rule reduces to FastTriggs
    np.testing.assert_allclose(e, e_f, rtol=1e-14)
    np.testing.assert_allclose(j, j_f, rtol=1e-14)
    e2, j2 = jo.Triggs()(kernel, b, a)
    assert bool(jnp.all(jnp.isfinite(e2))) and bool(jnp.all(jnp.isfinite(j2)))
    np.testing.assert_allclose(e2[0], 0.0)


def test_triggs_rejects_bad_min_d():
    with pytest.raises(ValueError, match="min_d"):
        jo.Triggs(min_d=0.0)
