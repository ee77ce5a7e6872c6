"""Implicit differentiation of a least-squares solution (one linear solve backwards).

At the solution X* the tangent gradient of the cost vanishes. With the chart
φ(δ, θ) = cost(X* ⊕ δ, θ) (θ = residual args, weights and kernel parameters, plus
anything the residual function closes over) the optimality condition ∇_δ φ(0, θ) = 0
and the implicit function theorem give

    dδ*/dθ = −H⁻¹ ∂²φ/∂δ∂θ,   H = ∂²φ/∂δ² (n, n) at δ = 0,

so for a cotangent v on X* (pulled back to the tangent space through δ ↦ X* ⊕ δ) the
backward pass solves H u = v once and returns θ̄ = −∇_θ (∇_δ φ · u). By default H is the
exact Hessian of the (robust, weighted) cost, so the gradient is exact for any residual;
``hessian="gauss_newton"`` uses J̃ᵀJ̃ from the whitened, kernel-corrected Jacobian instead
(first derivatives only: cheaper to compile, exact for zero-residual problems); it keeps the
coloured path's structure (block-diagonal or CSR H, see :mod:`jaxpose.optim._colouring`), so
with ``linear_solver=Cholesky()`` a large sparse problem is solved backwards by sparse
Cholesky too. The final cost's cotangent is propagated by the envelope theorem (∂cost/∂θ at
fixed X*). Gradients with respect to the initial params are zero; ``history`` has no
gradient. Reverse mode only (use ``adjoint="unrolled"`` for jvp). First order only:
differentiating the backward pass again (``jax.hessian``, ``jacfwd(jacrev(...))``,
``grad(grad(...))``) raises ``NotImplementedError`` rather than returning a wrong second
derivative (the backward pass treats the solution's dependence on θ as fixed); use
``adjoint="unrolled"`` for higher orders.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from ..lie import manifold
from ._colouring import normal_equations
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


def _fill(ref: PyTree, ct: PyTree) -> PyTree:
    leaves, treedef = jax.tree.flatten(ref)
    if ct is None:
        return jax.tree.unflatten(treedef, [jnp.zeros_like(x) for x in leaves])
    cts = treedef.flatten_up_to(ct)
    return jax.tree.unflatten(
        treedef, [jnp.zeros_like(x) if c is None else c for x, c in zip(leaves, cts)]
    )


@eqx.filter_custom_vjp
def _implicit(
    theta: tuple[PyTree, Problem],
    params0: PyTree,
    run: Callable[..., Solution],
    adjoint: ImplicitAdjoint,
) -> Solution:
    args, problem = theta
    return run(problem, params0, args)


@_implicit.def_fwd
def _implicit_fwd(
    perturbed: Any,
    theta: tuple[PyTree, Problem],
    params0: PyTree,
    run: Callable[..., Solution],
    adjoint: ImplicitAdjoint,
) -> tuple[Solution, Solution]:
    args, problem = theta
    sol = run(problem, params0, args)
    return sol, sol


@_implicit.def_bwd
def _implicit_bwd(
    sol: Solution,
    grad_obj: Any,
    perturbed: Any,
    theta: tuple[PyTree, Problem],
    params0: PyTree,
    run: Callable[..., Solution],
    adjoint: ImplicitAdjoint,
) -> Any:
    x_star = sol.params
    ct_params = None if grad_obj is None else grad_obj.params
    ct_cost = None if grad_obj is None else grad_obj.cost
    ct_init = None if grad_obj is None else grad_obj.initial_cost
    flat0, unravel = manifold.flat_tangent(x_star)

    def lift(eps: jax.Array) -> PyTree:
        return manifold.retract(x_star, unravel(eps))

    _, vjp_lift = jax.vjp(lift, flat0)
    (v,) = vjp_lift(_fill(x_star, ct_params))

    def phi(eps: jax.Array, th: tuple[PyTree, Problem]) -> jax.Array:
        a, prob = th
        return prob.cost(lift(eps), a)

    if adjoint.hessian == "exact":
        hess = jax.hessian(phi)(flat0, theta)
        hess = 0.5 * (hess + hess.T)
    else:
        args, problem = theta
        lin = problem.linearize_structured(x_star, args)
        hess, _ = normal_equations(lin.jac, lin.res)  # dense, BlockHessian or SparseHessian
    u = adjoint.linear_solver.solve(hess, -v, hess, -v, jnp.zeros_like(v))
    u = first_order_only(u, "least_squares(adjoint='implicit')")
    dtype = flat0.dtype
    c_cost = jnp.zeros((), dtype) if ct_cost is None else ct_cost
    c_init = jnp.zeros((), dtype) if ct_init is None else ct_init

    def psi(th: tuple[PyTree, Problem]) -> jax.Array:
        val, gu = jax.jvp(lambda e: phi(e, th), (flat0,), (u,))  # φ and ∇_δφ·u
        a, prob = th
        return c_cost * val + c_init * prob.cost(params0, a) - gu

    return eqx.filter_grad(psi)(theta)


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
    return _implicit((args, problem), params0, run, adjoint)


__all__ = ["ImplicitAdjoint", "UnrolledAdjoint", "first_order_only", "implicit_solve"]
