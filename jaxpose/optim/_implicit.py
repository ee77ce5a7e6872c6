"""Implicit differentiation of a least-squares solution, exact at every order.

At the solution X* the tangent gradient of the cost vanishes. With the chart
φ(δ, θ) = cost(X* ⊕ δ, θ) (θ = residual args, weights and kernel parameters, plus
anything the residual function closes over) the optimality condition ∇_δ φ(0, θ) = 0
and the implicit function theorem give the solution's tangent

    δ̇ = −H⁻¹ (∂²φ/∂δ∂θ · θ̇),   H = ∂²φ/∂δ² (n, n) at δ = 0,   Ẋ = d/dε (X* ⊕ ε δ̇).

This is a ``custom_jvp`` rule (one linear solve per tangent). Its right-hand side is
linear in θ̇ and the solve linear in it, so reverse mode is its transpose (one solve
with Hᵀ = H per cotangent), and the rule is written with differentiable operations on
the (differentiable) solution, so differentiating it again gives the exact second
derivative, and so on at any order: ``jax.grad``, ``jvp``, ``jacfwd``, ``jacrev``,
``jacfwd(jacrev)``, ``hessian``. ``cost`` and ``initial_cost`` carry their total
derivatives. Derivatives with respect to the initial params are zero (the solution does
not depend on them; where the solve did not converge, differentiating with respect to them
raises), ``history``, ``grad_norm`` and the counters have none.

By default H is the exact Hessian of the (robust, weighted) cost, so derivatives are exact
for any residual. On the coloured path (``jacobian="sparse"``, or ``"auto"`` choosing it)
H has JᵀJ's sparsity and is built from one Hessian-vector product per colour of its
columns (:func:`~jaxpose.optim._colouring.compressed_hessian`: a ``BlockHessian`` or a CSR
``SparseHessian``), not from n of them. ``hessian="gauss_newton"`` uses J̃ᵀJ̃ from the whitened,
kernel-corrected Jacobian instead: cheaper to compile, exact for zero-residual problems,
and it keeps the coloured path's structure (block-diagonal or CSR H, see
:mod:`jaxpose.optim._colouring`), so with ``linear_solver=Cholesky()`` a large sparse
problem is differentiated by sparse Cholesky too. Its second derivatives would miss the
Hessian's residual terms, so they raise ``NotImplementedError`` (never a wrong number).
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
from ..results import Results
from ._colouring import compressed_hessian, normal_equations
from ._linear import SVD, LinearSolver
from ._problem import Problem
from ._solution import Solution

PyTree = Any


class ImplicitAdjoint(eqx.Module):
    """Implicit-function-theorem adjoint.

    ``linear_solver`` solves H u = v (default :class:`SVD`: the pseudo-inverse, so gauge
    freedoms give the minimum-norm answer); ``hessian`` is ``"exact"`` or
    ``"gauss_newton"`` (see the module docstring)."""

    linear_solver: LinearSolver = SVD()
    hessian: str = eqx.field(default="exact", static=True)

    def __check_init__(self) -> None:
        if self.hessian not in ("exact", "gauss_newton"):
            raise ValueError(
                f"ImplicitAdjoint(hessian={self.hessian!r}): expected 'exact' or 'gauss_newton'"
            )


class UnrolledAdjoint(eqx.Module):
    """Plain reverse-mode autodiff through every iteration (checkpointed loop)."""


def first_order_only(x: PyTree, what: str) -> PyTree:
    """Identity on ``x`` that raises ``NotImplementedError`` (naming ``what``) when it is
    differentiated: marks values inside an implicit backward pass whose dependence on the
    inputs that rule does not carry, so a second derivative fails loudly instead of
    silently dropping terms."""

    @jax.custom_jvp
    def ident(y: PyTree) -> PyTree:
        return y

    @ident.defjvp
    def _refuse(primals: Any, tangents: Any) -> Any:
        raise NotImplementedError(
            f"{what}: the implicit derivative is exact at first order only; a second "
            f"derivative through it (jax.hessian, jacfwd(jacrev(...)), grad(grad(...))) is "
            f"not supported. Use the unrolled gradient for higher orders."
        )

    return ident(x)


def _not_converged(where: str, remedy: str) -> str:
    return (f"{where}: cannot differentiate the solution: the solver stopped without "
            f"converging (its status is not 'converged': check it), so the estimate is not "
            f"a stationary point and the implicit derivative would be wrong. {remedy}")


def converged_only(tangent: PyTree, status: jax.Array, where: str, remedy: str) -> PyTree:
    """``tangent`` (of a solution, inside its derivative rule), raising (``eqx.error_if``,
    also under jit and vmap) where it is nonzero for a problem whose ``status`` is not
    CONVERGED: the implicit function theorem holds at a stationary point only, and at an
    estimate a solver stopped at for another reason (budget spent, stalled, non-finite)
    its derivative is neither the optimum's nor that of the steps taken — a wrong number,
    never returned. ``remedy`` ends the message. ``status`` has the leaves' leading shape
    (a batch of problems) or is a scalar (:func:`refused_where_used`)."""
    return refused_where_used(tangent, status != Results.CONVERGED,
                              _not_converged(where, remedy))


def refused_where_used(tangent: PyTree, bad: jax.Array, message: str) -> PyTree:
    """``tangent``, raising ``message`` where it is nonzero for a problem where ``bad``
    (the leaves' leading shape, or a scalar) holds: one whose derivative does not exist.

    Each leaf passes through an identity ``jax.lax.custom_linear_solve`` whose solver
    checks it: in forward mode that is the tangent, in reverse mode (the transpose) the
    cotangent. So a bad problem of a vmapped batch raises only when something is
    differentiated through it: a loss that masks it out (zero cotangent) differentiates
    the others, exactly, as its contribution is zero (if the rule keeps the bad problem's
    tangent finite: 0 · NaN is NaN in a transpose)."""

    def leaf(t: Any) -> Any:
        if not eqx.is_inexact_array(t):
            return t
        mask = bad.reshape(bad.shape + (1,) * (jnp.ndim(t) - bad.ndim))

        def check(_: object, r: jax.Array) -> jax.Array:
            return eqx.error_if(r, jnp.any(mask & (r != 0)), message)

        return jax.lax.custom_linear_solve(lambda v: v, t, check, symmetric=True)

    return jax.tree.map(leaf, tangent)


def with_start(tangent: PyTree, t_start: PyTree, status: jax.Array, where: str,
               remedy: str) -> PyTree:
    """``tangent`` (a solution's, from its rule) plus its derivative along ``t_start``,
    the starting point's tangent (``None`` where a leaf has none): zero, exact for a
    converged problem, which does not depend on where it started; a problem stopped early
    does, so where ``status`` (a scalar) is not CONVERGED this raises as
    :func:`converged_only` does: in forward mode where ``t_start`` is nonzero, in reverse
    mode where the result's cotangent is. (Without this term a derivative with respect to
    the start alone never reached a check and came out zero.)"""
    starts = [t for t in jax.tree.leaves(t_start) if eqx.is_inexact_array(t)]
    if not starts:
        return tangent
    bad = status != Results.CONVERGED

    def zeros_checked(_: object, r: list[jax.Array]) -> list[jax.Array]:
        nonzero = jnp.any(jnp.stack([jnp.any(x != 0) for x in r]))
        return eqx.error_if([jnp.zeros_like(x) for x in r], bad & nonzero,
                            _not_converged(where, remedy))

    zero = jax.lax.custom_linear_solve(lambda v: v, starts, zeros_checked, symmetric=True)
    link = sum(jnp.sum(z) for z in zero)  # 0, linear in t_start: the outputs depend on it
    moved = jax.tree.map(
        lambda t: t + link.astype(t.dtype) if eqx.is_inexact_array(t) else t, tangent)
    return converged_only(moved, status, where, remedy)


def jvp_where(f: Callable[[PyTree], Any], tree: PyTree, t_tree: PyTree) -> tuple[Any, Any]:
    """``jax.jvp(f, (tree,), (t_tree,))`` where ``t_tree`` mirrors ``tree`` with ``None``
    for leaves without a tangent (symbolic zeros, non-arrays): only the others vary."""
    none = lambda x: x is None  # noqa: E731
    xs, treedef = jax.tree.flatten(tree, is_leaf=none)
    ts = jax.tree.flatten(t_tree, is_leaf=none)[0]
    live = [i for i, t in enumerate(ts) if t is not None]

    def f_live(vs: list[Any]) -> Any:
        full = list(xs)
        for i, v in zip(live, vs, strict=True):
            full[i] = v
        return f(jax.tree.unflatten(treedef, full))

    if not live:
        out = f(tree)
        return out, jax.tree.map(jnp.zeros_like, out)
    return jax.jvp(f_live, ([xs[i] for i in live],), ([ts[i] for i in live],))


Inner = Callable[[Callable[[jax.Array], jax.Array], jax.Array], jax.Array]
"""``inner(matvec, rhs) -> x``: the solver inside ``jax.lax.custom_linear_solve``."""


def checked(inner: Inner, message: str) -> Inner:
    """``inner`` raising ``message`` (``eqx.error_if``, also under jit) where it returns a
    non-finite solution for a finite right-hand side (a failed Cholesky, a singular LU, CG
    that has not converged): never a NaN derivative. The solver of a
    ``custom_linear_solve`` is evaluated, never transposed, so the check works in forward
    and reverse mode."""

    def solve(matvec: Callable[[jax.Array], jax.Array], rhs: jax.Array) -> jax.Array:
        zero_rhs = jnp.all(rhs == 0)  # a problem masked out of a batch: H need not be valid
        x = jnp.where(zero_rhs, 0, inner(matvec, rhs))
        failed = jnp.all(jnp.isfinite(rhs)) & ~jnp.all(jnp.isfinite(x))
        return eqx.error_if(x, failed, message)

    return solve


def _adjoint_solve(solver: LinearSolver, hess: Any, b: jax.Array) -> jax.Array:
    """H⁻¹ b by ``solver`` (``solve(jac, res, hess, grad, diag)`` returns
    −(hess + diag)⁻¹ grad). :class:`SVD` (the default) is the pseudo-inverse, defined for
    every H (a gauge freedom gives the minimum-norm derivative), and differentiated as
    such by lineax. Any other solver needs H nonsingular (Cholesky: positive definite):
    it runs inside ``jax.lax.custom_linear_solve`` (operator ``H @ v``, exact at every
    order) and raises (``eqx.error_if``, forward and reverse mode) where it returns a
    non-finite solution for a finite right-hand side, instead of a NaN derivative."""
    zero = jnp.zeros_like(b)
    if isinstance(solver, SVD):
        return -solver.solve(hess, b, hess, b, zero)
    message = (f"least_squares: cannot differentiate the solution: the adjoint's "
               f"{type(solver).__name__} solve with the Hessian H at the solution failed (H "
               f"is singular, or not positive definite for Cholesky). Either the solver "
               f"stopped away from a strict minimum (check the solution's status) or the "
               f"solution is not unique (a gauge freedom): the default "
               f"ImplicitAdjoint(linear_solver=SVD()) gives the minimum-norm derivative there.")

    def inner(_: object, rhs: jax.Array) -> jax.Array:
        return -solver.solve(hess, rhs, hess, rhs, zero)

    return jax.lax.custom_linear_solve(lambda v: hess @ v, b, checked(inner, message),
                                       symmetric=True)


@eqx.filter_custom_jvp
def _implicit(
    theta: tuple[PyTree, Problem],
    params0: PyTree,
    *,
    run: Callable[..., Solution],
    adjoint: ImplicitAdjoint,
) -> Solution:
    args, problem = theta
    return run(problem, params0, args)


@_implicit.def_jvp
@full_precision  # traced when differentiated, outside the entry point
def _implicit_jvp(
    primals: tuple[Any, Any],
    tangents: tuple[Any, Any],
    *,
    run: Callable[..., Solution],
    adjoint: ImplicitAdjoint,
) -> tuple[Solution, Any]:
    theta, params0 = primals
    t_theta, t_params0 = tangents
    sol = _implicit(theta, params0, run=run, adjoint=adjoint)  # differentiable again
    x_star = sol.params
    remedy = ("Give it more steps (max_steps) or looser tolerances, or differentiate the "
              "steps taken with adjoint='unrolled'.")
    converged = functools.partial(converged_only, status=sol.status, where="least_squares",
                                  remedy=remedy)
    flat0, unravel = manifold.flat_tangent(x_star)

    def lift(eps: jax.Array) -> PyTree:  # differentiated at most twice in eps, at 0
        return manifold.retract_quadratic(x_star, unravel(eps))

    def phi(eps: jax.Array, th: tuple[PyTree, Problem]) -> jax.Array:
        a, prob = th
        return prob.cost(lift(eps), a)

    # ∇_δφ at the solution (≈ 0, kept for the exact total derivative of the cost),
    # b = ∂(∇_δφ)/∂θ · θ̇ (linear in θ̇) and the cost's partial derivative ∂φ/∂θ · θ̇, from
    # one trace of the residuals (φ(0) is the cost at the solution)
    (_, grad0), (dcost, b) = jvp_where(lambda th: jax.value_and_grad(phi)(flat0, th), theta,
                                       t_theta)
    args, problem = theta
    if adjoint.hessian == "exact":
        mode, pattern = problem.jacobian_mode(x_star, args)
        # one Hessian-vector product per colour of H's columns, in JᵀJ's layout (blocks or
        # CSR; a pattern with neither, under SPARSE_MIN_SIZE unknowns, has a dense JᵀJ)
        if mode == "sparse" and (pattern.groups is not None or pattern.csr is not None):
            hess = compressed_hessian(lambda e: jax.grad(phi)(e, theta), flat0, pattern)
        else:
            hess = jax.hessian(phi)(flat0, theta)
            hess = 0.5 * (hess + hess.T)
    else:
        lin = problem.linearize_structured(x_star, args)
        hess, _ = normal_equations(lin.jac, lin.res)  # dense, BlockHessian or SparseHessian
        hess = first_order_only(hess, "least_squares(ImplicitAdjoint(hessian='gauss_newton'))")
    # checked before the solve in forward mode, after it in reverse (its transpose)
    eps_dot = -_adjoint_solve(adjoint.linear_solver, hess, converged(b))
    dcost, eps_dot = converged((dcost + jnp.dot(grad0, eps_dot), eps_dot))
    x_dot = jax.jvp(lift, (flat0,), (eps_dot,))[1]

    # total derivative of the initial cost (the cost's partial derivative is above)
    def initial_cost(th_p0: tuple[Any, Any]) -> jax.Array:
        (a, prob), p0 = th_p0
        return prob.cost(p0, a)

    _, dinit = jvp_where(initial_cost, (theta, params0), (t_theta, t_params0))
    x_dot, dcost = with_start((x_dot, dcost), t_params0, sol.status, "least_squares", remedy)
    t_sol = Solution(x_dot, None, None, None, dcost, dinit, None, None)  # None: no tangent
    return sol, t_sol


def implicit_solve(
    run: Callable[..., Solution],
    problem: Problem,
    params0: PyTree,
    args: PyTree,
    adjoint: ImplicitAdjoint,
) -> Solution:
    """Run ``run(problem, params0, args)`` with implicit gradients w.r.t. ``args`` and
    the problem's arrays (weights, kernel parameters, closed-over values)."""
    # Python numbers in ``args`` become arrays on their way through the custom rule below;
    # convert them first so the closure-converted function sees the same arguments
    args = jax.tree.map(
        lambda x: jnp.asarray(x) if isinstance(x, int | float | complex) else x, args
    )
    fn = eqx.filter_closure_convert(problem.residual_fn, params0, args)
    problem = eqx.tree_at(lambda p: p.residual_fn, problem, fn)
    if callable(problem.jacobian):
        jac = eqx.filter_closure_convert(problem.jacobian, params0, args)
        problem = eqx.tree_at(lambda p: p.jacobian, problem, jac)
    return _implicit((args, problem), params0, run=run, adjoint=adjoint)


__all__ = ["ImplicitAdjoint", "UnrolledAdjoint", "checked", "converged_only",
           "first_order_only", "implicit_solve", "jvp_where", "refused_where_used",
           "with_start"]
