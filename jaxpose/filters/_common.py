"""Shared pieces of the filters: result type, covariance checks, Gaussian helpers."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve

from ..dynamics._checks import as_array, check_psd
from ..dynamics._tangent import TangentSpace, tangent_space

Array = jax.Array


class FilterResult(eqx.Module):
    """Per-step posterior estimates of a run: ``x`` (N, …) (stacked states or group
    elements), ``P`` (N, k, k) covariances in the state's tangent coordinates, and
    ``ok`` (N,) False where the step produced non-finite values."""

    x: Any
    P: Array
    ok: Array


def noise_matrix(M: Any, name: str, strict: bool = False) -> Array:
    """Validate a (k, k) covariance (symmetric PSD, or PD when ``strict``)."""
    M = as_array(M, name, 2)
    check_psd(M, name, strict=strict)
    return M


def check_cov(P: Any, dim: int, name: str = "P") -> Array:
    """A (dim, dim) covariance for a state with ``dim`` tangent coordinates."""
    P = as_array(P, name, 2)
    if P.shape != (dim, dim):
        raise ValueError(
            f"{name}: expected shape ({dim}, {dim}) (state tangent size), got {tuple(P.shape)}"
        )
    check_psd(P, name)
    return P


def check_noise_dim(M: Array, dim: int, name: str, what: str) -> None:
    if M.shape != (dim, dim):
        raise ValueError(f"{name}: expected shape ({dim}, {dim}) ({what}), got {tuple(M.shape)}")


def symmetrize(P: Array) -> Array:
    return 0.5 * (P + P.T)


def state_space(x: Any) -> TangentSpace:
    return tangent_space(x)


def finite_tree(*trees: Any) -> Array:
    leaves = [leaf for t in trees for leaf in jax.tree.leaves(t)]
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in leaves]))


def gaussian_loglik(r: Array, L_inv: Array) -> Array:
    """log N(r; 0, S) with S = L Lᵀ, given the inverse lower Cholesky factor ``L_inv``
    (a matrix product per step instead of a LAPACK triangular solve); r (..., p)."""
    p = r.shape[-1]
    z = r @ L_inv.T
    logdet = -2.0 * jnp.sum(jnp.log(jnp.diag(L_inv)))
    return -0.5 * jnp.sum(z * z, -1) - 0.5 * logdet - 0.5 * p * jnp.log(2.0 * jnp.pi)


def kalman_gain(PHt: Array, S: Array) -> tuple[Array, Array]:
    """``K = PHᵀ S⁻¹`` by Cholesky of S; also returns the factor."""
    L = jnp.linalg.cholesky(symmetrize(S))
    K = cho_solve((L, True), PHt.T).T
    return K, L


def measurement_space(y: Any) -> TangentSpace:
    return tangent_space(y)
