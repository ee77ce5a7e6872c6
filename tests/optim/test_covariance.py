"""``jaxpose.optim.covariance``: the covariance of a least-squares solution.

References: closed forms ((AᵀWA)⁻¹ for linear residuals; Jr Ω⁻¹ Jrᵀ for a rotation prior,
with the SO(3) right Jacobian written out here), numpy's pseudo-inverse, and central finite
differences for the gradient.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.lie import SO3
from jaxpose.optim import covariance, least_squares


def _linear(params, args):
    a, b = args
    flat = jnp.concatenate([params["x"], params["y"].reshape(-1)])
    return a @ flat - b


def _setup(seed=0):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(9, 6))
    b = rng.normal(size=9)
    w = rng.normal(size=(9, 9))
    w = w @ w.T + 9 * np.eye(9)
    params = {"x": jnp.zeros(2), "y": jnp.zeros((2, 2))}
    return params, (jnp.asarray(a), jnp.asarray(b)), a, w


def test_linear_closed_form_flat_and_nested():
    params, args, a, w = _setup()
    cov = jax.jit(lambda p, s: covariance(_linear, p, s, weights=jnp.asarray(w)))(params, args)
    ref = np.linalg.inv(a.T @ w @ a)
    np.testing.assert_allclose(cov, ref, rtol=1e-10)
    nested = covariance(_linear, params, args, weights=jnp.asarray(w), flat=False)
    # ravel order: leaves sorted by key: "x" (2,), then "y" (2, 2)
    assert nested["x"]["x"].shape == (2, 2) and nested["x"]["y"].shape == (2, 2, 2)
    assert nested["y"]["y"].shape == (2, 2, 2, 2)
    np.testing.assert_allclose(nested["x"]["y"], ref[:2, 2:].reshape(2, 2, 2), rtol=1e-10)
    np.testing.assert_allclose(nested["y"]["y"], ref[2:, 2:].reshape(2, 2, 2, 2), rtol=1e-10)


def _jr(phi):
    th = np.linalg.norm(phi)
    k = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
    return np.eye(3) - (1 - np.cos(th)) / th**2 * k + (th - np.sin(th)) / th**3 * (k @ k)


def test_rotation_prior_in_the_tangent_chart():
    """r = Log(Z⁻¹X), ∂r/∂δ = Jr⁻¹(r) for X·Exp(δ): Cov = Jr(r) Ω⁻¹ Jr(r)ᵀ."""
    rng = np.random.default_rng(1)
    z = SO3.exp(jnp.asarray(rng.normal(size=3)))
    phi = np.array([0.3, -0.5, 0.9])
    x = z.compose(SO3.exp(jnp.asarray(phi)))
    om = rng.normal(size=(3, 3))
    om = om @ om.T + 3 * np.eye(3)

    def res(p, zz):
        return zz.inv().compose(p).log().data

    cov = covariance(res, x, z, weights=jnp.asarray(om))
    jr = _jr(phi)
    np.testing.assert_allclose(cov, jr @ np.linalg.inv(om) @ jr.T, rtol=1e-9)


def test_gradient_matches_finite_differences():
    params, (a, b), _, _ = _setup(2)

    def f(scale):
        return jnp.trace(covariance(_linear, params, (a * scale, b)))

    g = jax.grad(f)(1.3)
    h = 1e-6
    fd = (f(1.3 + h) - f(1.3 - h)) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6)
    # closed form: trace((s²AᵀA)⁻¹) = trace((AᵀA)⁻¹)/s² → derivative −2/s³·trace
    t = np.trace(np.linalg.inv(np.asarray(a).T @ np.asarray(a)))
    np.testing.assert_allclose(g, -2 * t / 1.3**3, rtol=1e-9)


def test_vmap_and_solution_input():
    params, (a, b), _, _ = _setup(3)
    scales = jnp.array([1.0, 2.0])
    covs = jax.vmap(lambda s: covariance(_linear, params, (a * s, b)))(scales)
    np.testing.assert_allclose(covs[1], covs[0] / 4, rtol=1e-10)
    sol = least_squares(_linear, params, (a, b))
    np.testing.assert_allclose(covariance(_linear, sol, (a, b)), covs[0], rtol=1e-10)
    c32 = covariance(_linear, jax.tree.map(lambda v: v.astype(jnp.float32), params),
                     (a.astype(jnp.float32), b.astype(jnp.float32)))
    assert c32.dtype == jnp.float32
    np.testing.assert_allclose(c32, covs[0], rtol=1e-4, atol=1e-6)


def test_rank_deficient_svd_and_cholesky_error():
    def res(p, _):
        return jnp.stack([p[0] + p[1], 2 * (p[0] + p[1]), p[2]])

    p = jnp.zeros(3)
    jac = np.array([[1.0, 1, 0], [2, 2, 0], [0, 0, 1]])
    np.testing.assert_allclose(covariance(res, p, method="svd"), np.linalg.pinv(jac.T @ jac),
                               atol=1e-12)
    with pytest.raises(eqx.EquinoxRuntimeError, match="singular"):
        covariance(res, p)
    with pytest.raises(ValueError, match="method"):
        covariance(res, p, method="qr")


def _fd(f, x, h=1e-6):
    return (np.asarray(f(x + h)) - np.asarray(f(x - h))) / (2 * h)


def test_svd_covariance_differentiates_at_repeated_and_dropped_eigenvalues():
    """The pseudo-inverse's derivative went through eigh's, infinite where eigenvalues
    repeat: an isotropic problem (JᵀJ = a²I) gave NaN in both modes. Now the constant-rank
    formula: equal to the Cholesky path's −C dH C at full rank, and to central differences
    when the dropped eigenspace moves (rank 2 of 3, both rows of J depend on θ)."""
    iso = lambda a: covariance(lambda x, a: a * (x - 1.0), jnp.zeros(3), a,  # noqa: E731
                               method="svd")
    for d in (jax.jacfwd(iso)(2.0), jax.jacrev(iso)(2.0)):
        np.testing.assert_allclose(d, -0.25 * np.eye(3), atol=1e-14)  # d/da a⁻² = −2a⁻³

    m = np.random.default_rng(3).normal(size=(2, 3))

    def deficient(t):  # J(θ) (2, 3): rank 2, its null direction turns with θ
        res = lambda x, t: (jnp.asarray(m) + t * jnp.array([[0.0, 1, 2], [1, 0, -1]])) @ x
        return covariance(res, jnp.zeros(3), t, method="svd")

    fd = _fd(deficient, 0.3)
    for d in (jax.jacfwd(deficient)(0.3), jax.jacrev(deficient)(0.3)):
        np.testing.assert_allclose(d, fd, rtol=1e-7, atol=1e-9)
    second = jax.jacfwd(jax.jacrev(deficient))(0.3)  # differentiates again
    np.testing.assert_allclose(second, _fd(jax.jacrev(deficient), 0.3), rtol=1e-6, atol=1e-8)


def test_svd_covariance_derivative_with_an_rcond_that_drops_nonzero_eigenvalues():
    """A user rcond drops eigenvalues that are not zero: the kept-dropped terms weigh
    1/(λ(λ − μ)), not 1/λ² (review: the zero-μ formula gave a gradient 26 % off)."""
    rng = np.random.default_rng(0)
    u, v = np.linalg.qr(rng.normal(size=(8, 5)))[0], np.linalg.qr(rng.normal(size=(5, 5)))[0]
    w = jnp.asarray(np.random.default_rng(5).normal(size=(5, 5)))
    for sv in ([1, 0.7, 0.3, 0.047, 0.04], [1.0, 0.5, 0.5, 0.05, 0.02]):  # a repeated pair
        a = jnp.asarray(u @ np.diag(sv) @ v.T)
        da = jnp.asarray(rng.normal(size=a.shape))
        cov = lambda t, a=a, da=da: covariance(  # noqa: E731
            lambda x, m: m @ x, jnp.zeros(5), a + t * da, method="svd", rcond=2e-3)
        fd = _fd(cov, 0.0)
        np.testing.assert_allclose(jax.jvp(cov, (0.0,), (1.0,))[1], fd, rtol=1e-6, atol=1e-6)
        loss = lambda t, cov=cov: jnp.sum(cov(t) * w)  # noqa: E731
        assert float(jax.grad(loss)(0.0)) == pytest.approx(float(_fd(loss, 0.0)), rel=1e-6)
