"""Covariance of a least-squares solution (Ceres' ``Covariance``, dense).

At the solution p*, the Gauss–Newton (Laplace) approximation gives
``Cov(δ) = (J̃ᵀJ̃)⁻¹`` for the tangent perturbation δ of ``p = p* ⊕ δ`` (groups: right
perturbation p*·Exp(δ); arrays: p* + δ), with J̃ the whitened, kernel-corrected Jacobian
of :meth:`jaxpose.optim.Problem.linearize` — the same matrix the solver uses. As in Ceres,
the residuals are taken as already whitened (no rescaling by the residual variance).

Layout: the flat matrix follows ``ravel_pytree(manifold.zero_tangent(params))`` (tangent
columns of group leaves, never storage columns), the same columns as the Jacobian. With
``flat=False`` the result is a nested pytree like a Hessian: for leaves a and b of the
tangent pytree, block ``[a][b]`` has shape ``(*shape_a, *shape_b)``.

Everything is differentiable (``jax.grad`` through the covariance works: the Cholesky
inverse and the Jacobian are differentiable functions of params and args).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._precision import full_precision
from ..lie import manifold
from ._correctors import Corrector
from ._linear import check_rcond
from ._problem import Problem, as_problem
from ._solution import Solution

PyTree = Any
Array = jax.Array
METHODS = ("cholesky", "svd")


@eqx.filter_jit
@full_precision
def covariance(
    residual_fn: Callable[[PyTree, PyTree], PyTree] | Problem,
    params: PyTree | Solution,
    args: PyTree = None,
    *,
    weights: PyTree = None,
    kernel: PyTree = None,
    corrector: Corrector | None = None,
    jacobian: str | Callable[..., Array] = "auto",
    method: str = "cholesky",
    rcond: float | None = None,
    flat: bool = True,
) -> Array | PyTree:
    """Covariance of ``params`` in the tangent chart at ``params`` (module docstring).

    Args:
        residual_fn: the residual function (or a :class:`Problem`) that was minimised.
        params: the solution: a params pytree or a :class:`Solution` (its ``params``).
        args, weights, kernel, corrector, jacobian: as in
            :func:`~jaxpose.optim.least_squares`.
        method: ``"cholesky"`` (H must be positive definite; a singular H raises at run
            time) or ``"svd"`` (pseudo-inverse of H, eigenvalues below
            ``rcond·λ_max`` dropped, like Ceres' ``SPARSE_QR``/``DENSE_SVD`` with
            ``min_reciprocal_condition_number``; default rcond: n·eps).
        flat: True: an (n, n) matrix in ``ravel_pytree`` tangent order; False: a nested
            pytree of blocks.

    Returns:
        The (n, n) covariance, or its nested-pytree form.

    Compiled with ``eqx.filter_jit`` like :func:`~jaxpose.optim.least_squares`: a repeated
    call with new arrays of the same shapes reuses the program.
    """
    if method not in METHODS:
        raise ValueError(f"covariance(method={method!r}): expected one of {METHODS}")
    if rcond is not None and method != "svd":
        raise ValueError(f"covariance(rcond={rcond!r}): only method='svd' drops small "
                         f"eigenvalues; got method={method!r}")
    check_rcond(rcond, "covariance(rcond)")
    if isinstance(params, Solution):
        params = params.params
    problem = as_problem(residual_fn, weights=weights, kernel=kernel, corrector=corrector,
                         jacobian=jacobian)
    problem.check(params, args)
    lin = problem.linearize(params, args)
    h = lin.jac.T @ lin.jac
    n = h.shape[0]
    if method == "cholesky":
        chol = jnp.linalg.cholesky(h)
        chol = eqx.error_if(
            chol, ~jnp.all(jnp.isfinite(chol)),
            "covariance: the Gauss-Newton matrix JᵀJ is singular or not positive definite "
            "(an unobserved direction or a gauge freedom); fix it with a prior or use "
            "method='svd'",
        )
        eye = jnp.eye(n, dtype=h.dtype)
        linv = jax.scipy.linalg.solve_triangular(chol, eye, lower=True)
        cov = linv.T @ linv
    else:
        cov = _psd_pinv(h, rcond)
    cov = 0.5 * (cov + cov.T)
    if flat:
        return cov
    return _nest(cov, manifold.zero_tangent(params))


def _eigen_pinv(h: Array, rcond: float | None) -> tuple[Array, Array, Array, Array]:
    """(C, w, v, keep) of symmetric PSD ``h``: the pseudo-inverse, the eigenvalues,
    eigenvectors and the kept ones, those above ``rcond·λ_max`` (default n·eps)."""
    n = h.shape[-1]
    w, v = jnp.linalg.eigh(h)
    tol = (n * jnp.finfo(h.dtype).eps if rcond is None else rcond) * jnp.max(w)
    keep = w > tol
    inv_w = jnp.where(keep, 1.0 / jnp.where(keep, w, 1.0), 0.0)
    return (v * inv_w) @ v.T, w, v, keep


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _psd_pinv(h: Array, rcond: float | None) -> Array:
    """Pseudo-inverse C of a symmetric PSD (n, n) ``h``: eigenvalues below
    ``rcond·λ_max`` (default n·eps) dropped."""
    return _eigen_pinv(h, rcond)[0]


@_psd_pinv.defjvp
def _psd_pinv_jvp(rcond: float | None, primals: tuple[Array], tangents: tuple[Array]
                  ) -> tuple[Array, Array]:
    """The derivative at constant rank, never dividing by a difference of two kept
    eigenvalues (eigh's own derivative does: infinite where they repeat, as in an
    isotropic problem, which made it NaN in both modes).

    Default ``rcond``: the dropped eigenvalues are zero to rounding, and
    dC = −C dH C + C² dH P + P dH C² (P = I − C H, Golub & Pereyra 1973), written with C
    and H only, so it differentiates again. A user ``rcond`` may drop eigenvalues μ > 0:
    the Daleckii–Krein form in the eigenbasis, weights −1/(λλ') between kept ones and
    1/(λ(λ − μ)) between kept and dropped (λ > μ) — its second derivative goes through
    eigh's, finite only where eigenvalues are distinct."""
    (h,), (dh,) = primals, tangents
    if rcond is None:
        c = _psd_pinv(h, rcond)
        p = jnp.eye(h.shape[-1], dtype=h.dtype) - c @ h
        cc = c @ c
        return c, -c @ dh @ c + cc @ dh @ p + p @ dh @ cc
    c, w, v, keep = _eigen_pinv(h, rcond)  # one eigendecomposition for C and its derivative
    lam = jnp.where(keep, w, 1.0)
    kk = keep[:, None] & keep[None, :]
    kd = keep[:, None] & ~keep[None, :]
    gap = jnp.where(kd, lam[:, None] - w[None, :], 1.0)  # λ − μ > 0 where kd
    f = jnp.where(kk, -1.0 / (lam[:, None] * lam[None, :]),
                  jnp.where(kd, 1.0 / (lam[:, None] * gap), 0.0))
    f = f + jnp.where(kd.T, f.T, 0.0)  # the dropped-kept block mirrors the kept-dropped
    return c, v @ (f * (v.T @ dh @ v)) @ v.T


def _nest(cov: Array, tangent: PyTree) -> PyTree:
    """(n, n) → nested pytree of blocks (*shape_a, *shape_b)."""
    leaves, treedef = jax.tree.flatten(tangent)
    sizes = [int(jnp.size(x)) for x in leaves]
    starts = [sum(sizes[:k]) for k in range(len(sizes))]
    rows = []
    for a, sa, la in zip(leaves, starts, sizes, strict=True):
        row = [
            cov[sa : sa + la, sb : sb + lb].reshape(*jnp.shape(a), *jnp.shape(b))
            for b, sb, lb in zip(leaves, starts, sizes, strict=True)
        ]
        rows.append(jax.tree.unflatten(treedef, row))
    return jax.tree.unflatten(treedef, rows)


__all__ = ["covariance"]
