"""Exact derivatives of a factor-graph solution, at every order, solved sparse.

At the solution X* the tangent gradient of the cost vanishes. With the chart
φ(δ, θ) = cost(X* ⊕ δ, θ) over the free variables (θ: every floating-point array of the
graph — measurements, information, factor data) the implicit function theorem gives the
solution's tangent

    δ̇ = −H⁻¹ (∂²φ/∂δ∂θ · θ̇),   Ẋ = d/dε (X* ⊕ ε δ̇),

with H = ∂²φ/∂δ² the exact Hessian of the (robust, weighted) cost. H has the block
pattern of J̃ᵀJ̃ (a factor only couples its own variables), so it is assembled in the
graph's CSR pattern from per-factor Hessians (one ``jax.hessian`` of a factor's cost,
vmapped over the group) and solved by the sparse direct solver inside
``jax.lax.custom_linear_solve`` (:func:`~jaxpose.graph._linear.solve_sparse_spd`).
Fixed variables have zero tangents (unit diagonal, zero right-hand side).

The rule is a ``custom_jvp``: its right-hand side is linear in θ̇ and the solve linear in
it, so reverse mode is its transpose (one sparse solve per cotangent), and every step is
a differentiable operation on the (differentiable) solution, so differentiating it again
gives exact second derivatives, and so on. ``cost`` and ``initial_cost`` carry their total
derivatives; the starting values get zero; counters, status and history have none.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from functools import partial
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._precision import full_precision
from ..lie import LieGroup
from ..optim._implicit import jvp_where
from ._analysis import tangent_dim
from ._factor import between_residual
from ._linear import solve_sparse_spd
from ._problem import (
    FactorGraph,
    Variables,
    _gather,
    _retract,
    _rho,
    assemble_blocks,
    cost,
    free_flat,
    retract_all,
)

Array = jax.Array


def exact_hessian_csr(graph: FactorGraph, variables: Variables) -> Array:
    """Values (nnz,) of the exact Hessian of the graph's cost in its tangent chart at
    ``variables``, in the graph's CSR pattern; rows and columns of fixed variables are
    zero except a unit diagonal."""
    st = graph.structure
    type_of = {n: k for k, n in enumerate(st.names)}
    per_factor = []
    for f in graph.factors:
        vals = [_gather(variables[s], i) for s, i in zip(f.slots, f.indices, strict=True)]

        def local_cost(deltas: tuple[Array, ...], point: tuple[Any, ...], data: Any,
                       sqrt: Any, f: Any = f) -> Array:
            moved = [_retract(p, d, "retract_quadratic")
                     for p, d in zip(point, deltas, strict=True)]
            r = f.residual(*moved, data)
            if sqrt is not None:
                r = sqrt.astype(r.dtype) @ r
            return 0.5 * _rho(f.kernel, r)

        def one(point: tuple[Any, ...], data: Any, sqrt: Any, f: Any = f,
                local_cost: Callable[..., Array] = local_cost) -> Any:
            zeros = tuple(jnp.zeros((tangent_dim(p),), p.dtype) for p in point)
            return jax.hessian(local_cost)(zeros, point, data, sqrt)

        if _is_between(f, vals):
            hess = jax.vmap(partial(_between_hessian, f.kernel))(*vals, f.data, f.sqrt_info)
        else:
            hess = jax.vmap(one)(tuple(vals), f.data, f.sqrt_info)
        masks = [st.free[type_of[s]][i] for s, i in zip(f.slots, f.indices, strict=True)]
        per_factor.append((hess, masks))

    def block(k: int, s: int, t: int) -> Array:
        hess, masks = per_factor[k]
        h = hess[s][t]
        return h * (masks[s][:, None, None] * masks[t][:, None, None]).astype(h.dtype)

    dtype = jax.tree.leaves(variables)[0].dtype
    values = st.pattern.csr(assemble_blocks(graph, block, dtype))
    return values.at[st.diag_pos].add(1.0 - free_flat(graph, dtype))


def _is_between(f: Any, vals: list[Any]) -> bool:
    """A :func:`~jaxpose.graph.between_residual` factor between two poses of one group."""
    return (f.residual is between_residual and len(vals) == 2
            and type(vals[0]) is type(vals[1]) and isinstance(vals[0], LieGroup))


def _between_hessian(kernel: Any, xi: LieGroup, xj: LieGroup, z: LieGroup,
                     sqrt: Any) -> tuple[tuple[Array, Array], tuple[Array, Array]]:
    """Exact Hessian blocks of ``½ρ(|S·Log(Z⁻¹(Xi·Exp δi)⁻¹(Xj·Exp δj))|²)`` at δ = 0,
    from a Hessian in the 6 (3) dimensions of the relative motion instead of the 12 (6)
    of the two poses.

    With T = Xi⁻¹Xj, (Xi·Exp δi)⁻¹(Xj·Exp δj) = T·Exp(a)·Exp(b), a = −Ad(T⁻¹)·δi = A·δi,
    b = δj, and by Baker–Campbell–Hausdorff Exp(a)·Exp(b) = Exp(u),
    u = a + b + ½[a, b] + O(3). The cost is h(u) = ½ρ(|S·Log(Z⁻¹·T·Exp u)|²), so with
    g = ∇h(0), G = ∇²h(0) and M_pq = gᵀ[e_p, e_q]: H_ii = AᵀGA, H_ij = AᵀG + ½AᵀM,
    H_jj = G. Exact at every (X, θ), hence differentiable again like the generic rule.
    """
    group = type(xi)
    rel = xi.inv().compose(xj)
    base = z.inv().compose(rel)
    dim = group.tangent_dim

    def h(u: Array) -> Array:
        r = base.retract_quadratic(u).log().data
        if sqrt is not None:
            r = sqrt.astype(r.dtype) @ r
        return 0.5 * _rho(kernel, r)

    zero = jnp.zeros((dim,), rel.dtype)
    eye = jnp.eye(dim, dtype=rel.dtype)
    g, hh = jax.vmap(lambda e: jax.jvp(jax.grad(h), (zero,), (e,)), out_axes=(None, 0))(eye)
    hh = 0.5 * (hh + hh.T)
    a = -rel.inv().adj_matrix()
    m = jnp.einsum("k,kqp->pq", g, _structure_constants(group, rel.dtype))
    hij = a.T @ hh + 0.5 * a.T @ m
    return ((a.T @ hh @ a, hij), (hij.T, hh))


def _structure_constants(group: type, dtype: Any) -> Array:
    """(d, d, d) ``c[k, q, p] = [e_p, e_q]_k`` of the group's Lie algebra, from
    ``ad(e_p) = d/ds Ad(Exp(s·e_p))`` at s = 0 (a constant, computed once per group and
    dtype)."""
    return jnp.asarray(_structure_constants_np(group, jnp.dtype(dtype).name))


@functools.cache
def _structure_constants_np(group: type, dtype: str) -> np.ndarray:
    # [e_p, e_q] = vee(ê_p·ê_q − ê_q·ê_p) in NumPy from the d basis matrices ê (one small
    # compiled call: differentiating Ad(Exp(·)) op by op compiled ~100 tiny XLA programs,
    # ~2.5 s of every trace that differentiates a between factor)
    d = group.tangent_dim
    hat = jax.jit(group._hat).lower(jax.ShapeDtypeStruct((d, d), dtype)).compile()
    hats = np.asarray(hat(np.eye(d, dtype=dtype)), np.float64)  # runs now, even inside a trace
    brackets = hats[:, None] @ hats[None, :] - hats[None, :] @ hats[:, None]  # [p, q]
    coords = np.linalg.lstsq(hats.reshape(d, -1).T, brackets.reshape(d * d, -1).T,
                             rcond=None)[0]  # (k, p·d + q)
    return coords.reshape(d, d, d).transpose(0, 2, 1).astype(dtype)


@eqx.filter_custom_jvp
def _differentiable(graph: FactorGraph, x0: Variables, *, run: Callable[..., Any],
                    options: dict[str, Any]) -> Any:
    return run(graph, x0, **options)


@_differentiable.def_jvp
@full_precision  # traced when differentiated, outside the entry point
def _differentiable_jvp(primals: tuple[Any, Any], tangents: tuple[Any, Any], *,
                        run: Callable[..., Any], options: dict[str, Any]) -> Any:
    graph, x0 = primals
    t_graph, t_x0 = tangents
    sol = _differentiable(graph, x0, run=run, options=options)  # differentiable again
    xs = sol.variables
    dtype = sol.cost.dtype
    zero = jnp.zeros((graph.structure.size,), dtype)
    free = free_flat(graph, dtype)

    def phi(delta: Array, g: FactorGraph) -> Array:
        return cost(g, retract_all(g, xs, delta, "retract_quadratic"))

    # ∇_δφ at the solution (≈ 0, kept for the exact total derivative of the cost) and
    # b = ∂(∇_δφ)/∂θ · θ̇
    grad0, b = jvp_where(lambda g: jax.grad(phi)(zero, g), graph, t_graph)
    st = graph.structure
    hess = exact_hessian_csr(graph, xs)
    eps_dot = -solve_sparse_spd(hess, st.csr_indices, st.csr_indptr, b * free)
    x_dot = jax.jvp(lambda d: retract_all(graph, xs, d, "retract_quadratic"), (zero,),
                    (eps_dot,))[1]
    _, dcost = jvp_where(lambda g: cost(g, xs), graph, t_graph)
    dcost = dcost + jnp.dot(grad0, eps_dot)
    _, dinit = jvp_where(lambda gx: cost(*gx), (graph, x0), (t_graph, t_x0))
    t_sol = type(sol)(x_dot, dcost, dinit, None, None, None, None)  # None: no tangent
    return sol, t_sol


def solve_differentiable(run: Callable[..., Any], graph: FactorGraph, x0: Variables,
                         **options: Any) -> Any:
    """``run(graph, x0, **options)`` (a :class:`~jaxpose.graph.GraphSolution`) with the
    exact, any-order derivatives of the module docstring."""
    return _differentiable(graph, x0, run=run, options=options)


__all__ = ["exact_hessian_csr", "solve_differentiable"]
