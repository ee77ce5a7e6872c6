"""Exact derivatives of a factor-graph solution, at every order, solved sparse.

At the solution X* the tangent gradient of the cost vanishes. With the chart
φ(δ, θ) = cost(X* ⊕ δ, θ) over the free variables (θ: every floating-point array of the
graph — measurements, information, factor data) the implicit function theorem gives the
solution's tangent

    δ̇ = −H⁻¹ (∂²φ/∂δ∂θ · θ̇),   Ẋ = d/dε (X* ⊕ ε δ̇),

with H = ∂²φ/∂δ² the exact Hessian of the (robust, weighted) cost. H has the block
pattern of J̃ᵀJ̃ (a factor only couples its own variables), so it is assembled in the
graph's CSR pattern from per-factor Hessians (one ``jax.hessian`` of a factor's cost,
vmapped over :data:`HESSIAN_CHUNK` factors at a time; closed forms for between factors,
:func:`_between_hessian`, and BAL reprojections, :func:`_bal_hessian`) and solved by the
forward's linear solver (:func:`_tangent_solve`) inside ``jax.lax.custom_linear_solve``
(:func:`~jaxpose.graph._linear.solve_sparse_spd`).
Fixed variables have zero tangents (unit diagonal, zero right-hand side). A backward solve
that fails (H not positive definite, CG not converged) raises
(:func:`~jaxpose.optim._implicit.checked`): never a NaN derivative.

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
from ..lie import SE3, LieGroup
from ..lie._base import skew, small_matmul
from ..optim._implicit import checked, converged_only, jvp_where, with_start
from ._analysis import tangent_dim
from ._factor import between_residual
from ._linear import (
    block_jacobi,
    pcg_spd,
    solve_dense,
    solve_sparse_direct,
    solve_sparse_spd,
)
from ._pattern import scatter_blocks
from ._problem import (
    FactorGraph,
    Variables,
    _gather,
    _retract,
    _rho,
    cost,
    free_flat,
    group_blocks,
    retract_all,
    stored_together,
)
from ._reprojection import pixel_terms, reprojection_residual
from ._schur import (
    SchurParts,
    add_group,
    reduced_solver,
    schur_parts_by_group,
    schur_step,
)

Array = jax.Array


HESSIAN_CHUNK = 1024
"""Factors per step of the exact Hessian's loop: its per-factor temporaries (dozens of
(chunk, d, d) arrays from differentiating twice) stay this many factors deep instead of
the whole graph's, which keeps the backward's peak memory near the forward's. Each step
costs the dispatch of its XLA kernels: on parking-garage the exact Hessian takes ~17 ms
in steps of 1024 against ~14 ms in one step, whose temporaries are 3.7x larger (24.6 vs
6.6 MB, more than the whole forward solve's 15.6 MB)."""


def exact_hessian_csr(graph: FactorGraph, variables: Variables) -> Array:
    """Values (nnz,) of the exact Hessian of the graph's cost in its tangent chart at
    ``variables``, in the graph's CSR pattern; rows and columns of fixed variables are
    zero except a unit diagonal."""
    st = graph.structure
    dtype = jax.tree.leaves(variables)[0].dtype
    # zeros that depend on the solution: a constant accumulator is materialised at the
    # start of the program and lives through the whole forward solve (+25 % peak memory
    # on parking-garage); a non-finite solution gives a non-finite Hessian, as it should
    zero = 0.0 * jax.tree.leaves(variables)[0].reshape(-1)[0]
    blocks = [b + zero.astype(b.dtype) for b in st.pattern.zeros(dtype)]
    for k in range(len(graph.factors)):
        blocks = _add_factor_hessians(graph, k, variables, blocks)
    values = st.pattern.csr(st.pattern.without_fixed(blocks, st.free))
    return values.at[st.diag_pos].add(1.0 - free_flat(graph, dtype))


def _add_factor_hessians(graph: FactorGraph, k: int, variables: Variables,
                         blocks: list[Array]) -> list[Array]:
    """``blocks`` plus the exact per-factor Hessians of factor group ``k`` (blocks of
    fixed variables included), in chunks (:func:`_over_chunks`)."""
    def add(blocks: list[Array], hess: Any, take: Callable[[Any], Any], new: Array,
            start: Array) -> list[Array]:
        return scatter_blocks(blocks, group_blocks(graph, k, lambda _, s, t: hess[s][t], take),
                              keep=new)

    return _over_chunks(graph, k, variables, blocks, add)


def _over_chunks(graph: FactorGraph, k: int, variables: Variables, carry: Any,
                 consume: Callable[..., Any]) -> Any:
    """Fold ``consume(carry, hess, take, new, start)`` over factor group ``k``'s exact
    per-factor Hessian blocks (:func:`_factor_hessians`), :data:`HESSIAN_CHUNK` factors
    per loop step: ``hess[s][t]`` (chunk, d_s, d_t) of the factors ``start + i``,
    ``take(a)`` the chunk's rows of a per-factor array, ``new`` (chunk,) the rows no
    earlier step held. The last chunk ends at the last factor and overlaps its
    predecessor: sums must drop the rows that are not ``new``. An empty group adds
    nothing."""
    f = graph.factors[k]
    if f.count == 0:
        return carry
    size = min(HESSIAN_CHUNK, f.count)

    def step(i: Array, carry: Any) -> Any:
        start = jnp.minimum(i * size, f.count - size)
        new = jnp.arange(size) + start >= i * size
        take = partial(jax.tree.map, lambda a: jax.lax.dynamic_slice_in_dim(a, start, size))
        hess = _factor_hessians(f, variables, take(f.indices), take(f.data),
                                take(f.sqrt_info))
        return consume(carry, hess, take, new, start)

    return jax.lax.fori_loop(0, -(-f.count // size), step, carry)


def _factor_hessians(f: Any, variables: Variables, idx: tuple[Array, ...], data: Any,
                     sqrt: Any) -> list[list[Array]]:
    """``hess[s][t]`` (m, d_s, d_t): exact Hessian blocks of the factors of group ``f``
    with variable indices ``idx``, ``data`` and ``sqrt`` information, the blocks of fixed
    variables included: consumers zero those after summing (a mask here is fused into
    every block's computation by XLA:CPU, which doubled parking-garage's exact Hessian)."""
    vals = [_gather(variables[s], i) for s, i in zip(f.slots, idx, strict=True)]
    return _factor_hessian(f, vals)(vals, data, sqrt)


def _factor_hessian(f: Any, values: list[Any]) -> Callable[..., Any]:
    """``(points, data, sqrt) -> hess`` for a batch of factors of ``f``'s kind:
    ``hess[s][t]`` (batch, d_s, d_t) is the Hessian of the factor's ½ρ(|S·r|²) in the
    tangent charts of its slots s and t at δ = 0."""
    if _is_between(f, values):
        def between(vals: list[Any], data: Any, sqrt: Any) -> list[list[Array]]:
            (hii, hij), (hji, hjj) = jax.vmap(partial(_between_hessian, f.kernel))(
                *vals, data, sqrt)
            hii, hij, hji, hjj = stored_together((hii, hij, hji, hjj))
            return [[hii, hij], [hji, hjj]]

        return between
    if _is_bal_reprojection(f, values):
        def reprojection(vals: list[Any], data: Any, sqrt: Any) -> list[list[Array]]:
            hess = jax.vmap(partial(_bal_hessian, f.kernel))(*vals, data, sqrt)
            flat = stored_together([b for row in hess for b in row])
            return [list(flat[3 * s:3 * s + 3]) for s in range(3)]

        return reprojection

    def local_cost(deltas: tuple[Array, ...], point: tuple[Any, ...], data: Any,
                   sqrt: Any) -> Array:
        moved = [_retract(p, d, "retract_quadratic") for p, d in zip(point, deltas, strict=True)]
        r = f.residual(*moved, data)
        if sqrt is not None:
            r = sqrt.astype(r.dtype) @ r
        return 0.5 * _rho(f.kernel, r)

    def one(point: tuple[Any, ...], data: Any, sqrt: Any) -> Any:
        zeros = tuple(jnp.zeros((tangent_dim(p),), p.dtype) for p in point)
        return jax.hessian(local_cost)(zeros, point, data, sqrt)

    return lambda vals, data, sqrt: jax.vmap(one)(tuple(vals), data, sqrt)


def _is_between(f: Any, vals: list[Any]) -> bool:
    """A :func:`~jaxpose.graph.between_residual` factor between two poses of one group."""
    return (f.residual is between_residual and len(vals) == 2
            and type(vals[0]) is type(vals[1]) and isinstance(vals[0], LieGroup))


def _between_hessian(kernel: Any, xi: LieGroup, xj: LieGroup, z: LieGroup,
                     sqrt: Any) -> tuple[tuple[Array, Array], tuple[Array, Array]]:
    """Exact Hessian blocks of ``½ρ(|S·Log(Z⁻¹(Xi·Exp δi)⁻¹(Xj·Exp δj))|²)`` at δ = 0,
    from a Hessian in the 6 (3) dimensions of the relative motion instead of the 12 (6)
    of the two poses, in closed form from first derivatives of Jr⁻¹.

    With T = Xi⁻¹Xj, (Xi·Exp δi)⁻¹(Xj·Exp δj) = T·Exp(a)·Exp(b), a = −Ad(T⁻¹)·δi = A·δi,
    b = δj, and by Baker–Campbell–Hausdorff Exp(a)·Exp(b) = Exp(u),
    u = a + b + ½[a, b] + O(3). The cost is h(u) = ½ρ(s), s = |S·r(u)|²,
    r(u) = Log(Z⁻¹·T·Exp u), so with g = ∇h(0), G = ∇²h(0) and M_pq = gᵀ[e_p, e_q]:
    H_ii = AᵀGA, H_ij = AᵀG + ½AᵀM, H_jj = G. From Exp r(u) = Z⁻¹T·Exp u,
    ∂r/∂u = Jr⁻¹(r(u))·Jr(u), so at u = 0 (J = Jr⁻¹(r), Jr(u) = I − ½ad(u) + …)
    yᵀ∂²r[v, w] = wᵀK·J·v − ½(Jᵀy)ᵀ[v, w] with K = ∂(Jr⁻¹(r)ᵀy)/∂r; the bracket term is
    antisymmetric, so Σ yₖ∇²rₖ = sym(K·J), and with y = Sᵀ(S·r):
    G = ρ′·(JᵀSᵀSJ + sym(K·J)) + 2ρ″·(Jᵀy)(Jᵀy)ᵀ, g = ρ′·Jᵀy. Exact at every (X, θ)
    and built from differentiable operations, hence differentiable again like the
    generic rule (K from the group's ``_jl_inv_principal_dual``: closed forms for SE3 and SE2,
    one forward-mode Jacobian of Jr⁻¹ otherwise — not a second-order pass through Log,
    Exp and the products, which took twice the time on parking-garage).
    """
    group = type(xi)
    rel = xi.inv().compose(xj)
    r = z.inv().compose(rel).log().data
    if sqrt is None:
        sr, y = r, r
    else:  # products by elements: batched 6×6 dots are slow on XLA:CPU
        sqrt = sqrt.astype(r.dtype)
        sr = jnp.sum(sqrt * r, -1)
        y = jnp.sum(sqrt * sr[:, None], 0)  # Sᵀ·S·r

    # J = Jr⁻¹(r) = Jl⁻¹(−r) (|r's angle| ≤ π), Jᵀy and K = −∂(Jl⁻¹ᵀy)/∂ξ at ξ = −r
    jac, jty, dual = group._jl_inv_principal_dual(-r, y)
    kmat = -dual
    sjac = jac if sqrt is None else small_matmul(sqrt, jac)
    kj = small_matmul(kmat, jac)
    hh = small_matmul(sjac.T, sjac) + 0.5 * (kj + kj.T)
    if kernel is not None:
        s = jnp.sum(sr * sr)
        d1, d2 = kernel.derivative(s), kernel.second_derivative(s)
        hh = d1 * hh + 2.0 * d2 * jty[:, None] * jty[None, :]
        jty = d1 * jty
    a = -rel.inv().adj_matrix()
    m = jnp.einsum("k,kqp->pq", jty, _structure_constants(group, rel.dtype))
    at_hh = small_matmul(a.T, hh)
    hij = at_hh + 0.5 * small_matmul(a.T, m)
    return ((small_matmul(at_hh, a), hij), (hij.T, hh))


def _is_bal_reprojection(f: Any, vals: list[Any]) -> bool:
    """A :func:`~jaxpose.graph.reprojection_residual` factor (pose, intrinsics, point)."""
    return (f.residual is reprojection_residual and len(vals) == 3
            and isinstance(vals[0], SE3))


def _bal_hessian(kernel: Any, pose: SE3, intrinsics: Array, point: Array, z: Array,
                 sqrt: Any) -> list[list[Array]]:
    """Exact Hessian blocks ``h[s][t]`` (slots pose (6: ρ, φ), intrinsics (3), point (3))
    of one BAL reprojection factor's ``½ρ(|S·r|²)`` at δ = 0, through the six numbers the
    residual depends on: u = (P, f, k1, k2), P = R·X + t the point in the camera.

    With c(u) the factor's cost, g = ∇c, G = ∇²c (its blocks from
    :func:`_pixel_cost_derivatives`), A = ∂u/∂δ and w = Rᵀ·∂c/∂P: H = AᵀGA + the second-order terms
    of P. Right-perturbed, P(δ) = R·Exp(ξ)·(X + δX) + t and to second order
    Exp(ξ)·Y = Y + ρ + φ×Y + ½φ×ρ + ½φ×(φ×Y), so A's P rows are R·[I, −[X]×, 0, I] and
    the terms wᵀ∂²(RᵀP) are (φ, ρ): −½[w]×, (φ, φ): ½(wXᵀ + Xwᵀ) − (w·X)·I,
    (φ, δX): −[w]× (and their transposes). Differentiable again like the generic rule.
    """
    rot = pose.rotation().matrix()
    pc = jnp.sum(rot * point, -1) + pose.translation()
    g_pt, g_pp, g_pi, g_ii = _pixel_cost_derivatives(kernel, pc, intrinsics, z, sqrt)
    # products by elements (small_matmul): batched small dots are slow on XLA:CPU.
    # With K = [X]× (Kᵀ = −K): ∂(RᵀP)/∂ξ = [I, −K], so AᵀGA's pose rows are
    # [[M, −MK], [KM, −KMK]] (M = RᵀG_PP R) and the (φ, ·) rows pick up the terms above
    eye = jnp.eye(3, dtype=pc.dtype)
    w = jnp.sum(rot * g_pt[:, None], 0)
    m = small_matmul(small_matmul(rot.T, g_pp), rot)  # point–point
    n = small_matmul(rot.T, g_pi)  # point–intrinsics
    k = skew(point)
    w_x = skew(w)
    km = small_matmul(k, m)
    phi_phi = (0.5 * (w[:, None] * point[None, :] + point[:, None] * w[None, :])
               - jnp.sum(w * point) * eye - small_matmul(km, k))
    rho_phi = 0.5 * w_x - small_matmul(m, k)
    pose_pose = jnp.concatenate([jnp.concatenate([m, rho_phi], axis=1),
                                 jnp.concatenate([rho_phi.T, phi_phi], axis=1)], axis=0)
    pose_intr = jnp.concatenate([n, small_matmul(k, n)], axis=0)
    pose_point = jnp.concatenate([m, km - w_x], axis=0)
    return [[pose_pose, pose_intr, pose_point],
            [pose_intr.T, g_ii, n.T],
            [pose_point.T, n, m]]


def _pixel_cost_derivatives(kernel: Any, pc: Array, intrinsics: Array, z: Array,
                            sqrt: Any) -> tuple[Array, Array, Array, Array]:
    """``(g_P (3,), G_PP, G_PI, G_II (3, 3))``: the gradient in P and the Hessian blocks of
    c(u) = ½ρ(|S·(pixel(u) − z)|²) in u = (P, I), I = (f, k1, k2)
    (:func:`~jaxpose.graph._reprojection.pixel`), in closed form.

    With p = −P_xy/P_z, pixel = f·D(r²)·p, D = 1 + k1·r² + k2·r⁴, r² = |p|², y = SᵀS·r and
    J_P = J_p·B (J_p = ∂pixel/∂p, B = ∂p/∂P), J_I = ∂pixel/∂I: the Hessian of ½|S·r|² is
    JᵀSᵀSJ plus Σₖ yₖ∇²pixelₖ, which is BᵀΨ_ppB, BᵀΨ_pI and Ψ_II from Ψ = ∇²(yᵀpixel) in
    (p, I), and in the P block Σⱼ aⱼ∇²pⱼ = (e_z vᵀ + v e_zᵀ)/P_z² (a = J_pᵀy,
    v = (a, a·p)); a kernel makes it ρ′·(…) + 2ρ″·(Jᵀy)(Jᵀy)ᵀ."""
    dtype = pc.dtype
    f, k2 = intrinsics[0], intrinsics[2]
    iz = 1.0 / pc[2]
    p, r2, d, d1, jp, bp, j_in = pixel_terms(pc, intrinsics)
    eye2 = jnp.eye(2, dtype=dtype)
    pp = p[:, None] * p[None, :]
    zero = jnp.zeros((), dtype)
    j_pt = small_matmul(jp, bp)  # ∂pixel/∂P (2, 3)
    r = f * d * p - z
    if sqrt is None:
        s_pt, s_in, y = j_pt, j_in, r
    else:
        sqrt = sqrt.astype(dtype)
        s_pt, s_in = small_matmul(sqrt, j_pt), small_matmul(sqrt, j_in)
        y = jnp.sum(sqrt * jnp.sum(sqrt * r, -1)[:, None], 0)  # SᵀS·r
    h = jnp.sum(y * p)
    yp = y[:, None] * p[None, :]
    psi_pp = f * (2.0 * d1 * (yp + yp.T + h * eye2) + 8.0 * k2 * h * pp)
    psi_pi = jnp.stack([d * y + 2.0 * d1 * h * p, f * (r2 * y + 2.0 * h * p),
                        f * r2 * (r2 * y + 4.0 * h * p)], axis=1)
    hr2, hr4 = h * r2, h * r2 * r2  # Ψ_II: only ∂²/∂f∂k1 = h·r², ∂²/∂f∂k2 = h·r⁴
    psi_ii = jnp.stack([jnp.stack([zero, hr2, hr4]), jnp.stack([hr2, zero, zero]),
                        jnp.stack([hr4, zero, zero])])
    a = jnp.sum(jp * y[:, None], 0)
    v = jnp.concatenate([a, jnp.sum(a * p)[None]]) * (iz * iz)
    e_z = jnp.asarray([0.0, 0.0, 1.0], dtype)
    g_pt, g_in = jnp.sum(j_pt * y[:, None], 0), jnp.sum(j_in * y[:, None], 0)
    h_pp = (small_matmul(s_pt.T, s_pt) + small_matmul(small_matmul(bp.T, psi_pp), bp)
            + e_z[:, None] * v[None, :] + v[:, None] * e_z[None, :])
    h_pi = small_matmul(s_pt.T, s_in) + small_matmul(bp.T, psi_pi)
    h_ii = small_matmul(s_in.T, s_in) + psi_ii
    if kernel is not None:
        s = jnp.sum(jnp.square(r if sqrt is None else jnp.sum(sqrt * r, -1)))
        d1k, d2k = kernel.derivative(s), kernel.second_derivative(s)
        outer = lambda x, w: 2.0 * d2k * x[:, None] * w[None, :]  # noqa: E731
        h_pp = d1k * h_pp + outer(g_pt, g_pt)
        h_pi = d1k * h_pi + outer(g_pt, g_in)
        h_ii = d1k * h_ii + outer(g_in, g_in)
        g_pt = d1k * g_pt
    return g_pt, h_pp, h_pi, h_ii


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
    _refuse_open_gauge(graph)
    sol = _differentiable(graph, x0, run=run, options=options)  # differentiable again
    xs = sol.variables

    remedy = "Give it more steps (Stopping(max_steps=...)) or looser tolerances."
    converged = functools.partial(converged_only, status=sol.status, where="graph.solve",
                                  remedy=remedy)

    dtype = sol.cost.dtype
    zero = jnp.zeros((graph.structure.size,), dtype)
    free = free_flat(graph, dtype)

    # ∇_δφ at the solution (≈ 0, kept for the exact total derivative of the cost),
    # b = ∂(∇_δφ)/∂θ · θ̇ and the cost's partial derivative ∂φ/∂θ · θ̇, from one trace of
    # the residuals (φ(0) is the cost at the solution)
    (_, grad0), (dcost, b) = jvp_where(
        lambda g: jax.value_and_grad(_chart_cost, argnums=2)(g, xs, zero), graph, t_graph)
    # checked before the solve in forward mode, after it in reverse (its transpose)
    eps_dot = -_tangent_solve(graph, options, xs, converged(b * free))
    dcost, eps_dot = converged((dcost + jnp.dot(grad0, eps_dot), eps_dot))
    x_dot = jax.jvp(lambda d: retract_all(graph, xs, d, "retract_quadratic"), (zero,),
                    (eps_dot,))[1]
    _, dinit = jvp_where(lambda gx: cost(*gx), (graph, x0), (t_graph, t_x0))
    x_dot, dcost = with_start((x_dot, dcost), t_x0, sol.status, "graph.solve", remedy)
    t_sol = type(sol)(x_dot, dcost, dinit, None, None, None, None)  # None: no tangent
    return sol, t_sol


def _chart_cost(graph: FactorGraph, xs: Variables, delta: Array) -> Array:
    """φ(δ) = cost(X ⊕ δ): the graph's cost in the tangent chart at ``xs`` (the quadratic
    retraction, exact to second order; fixed variables do not move), δ (N,)."""
    return cost(graph, retract_all(graph, xs, delta, "retract_quadratic"))


def _refuse_open_gauge(graph: FactorGraph) -> None:
    """Raise where the graph has a gauge freedom (:func:`open_gauge`): its solution is not
    unique, H is singular and the solution's derivative undefined — a sparse
    factorisation would return large, meaningless numbers."""
    gauge = open_gauge(graph)
    if gauge is not None:
        why, fix = gauge
        raise ValueError(
            f"graph.solve: cannot differentiate the solution: {why} (a gauge freedom); the "
            f"solution is not unique and its derivative is undefined. To differentiate, "
            f"{fix}.")


def open_gauge(graph: FactorGraph) -> tuple[str, str] | None:
    """``(why, fix)`` where the graph's cost is certainly invariant under a motion of all
    its variables (a gauge freedom, H singular), else None. Recognised: graphs of between
    factors only with no fixed pose, and of BAL reprojections only with fewer than two
    fixed cameras (the scale stays free). Other graphs (priors, custom factors) are the
    user's to fix."""
    st = graph.structure
    fixed = dict(zip(st.names, st.fixed_counts, strict=True))
    factors = graph.factors
    if all(f.residual is between_residual for f in factors) and not any(
            fixed[s] for f in factors for s in f.slots):
        why = ("every factor is a between factor and no pose is fixed, so moving all poses "
               "by one rigid motion leaves the cost unchanged")
        fix = "fix a pose (FactorGraph(..., fixed={'pose': [0]})) or add a prior factor"
    elif all(f.name == "reprojection_bal" for f in factors) and fixed.get("pose", 0) < 2:
        why = ("every factor is a reprojection and fewer than two cameras are fixed, so a "
               "similarity transform of cameras and points leaves the cost unchanged")
        fix = ("fix two cameras whose values you trust (bundle_adjustment_problem(..., "
               "fixed_cameras=[0, 1]) holds them at their current values) or add priors")
    else:
        return None
    return why, fix


BACKWARD_RTOL = {"float64": 1e-10, "float32": 1e-5}
"""Relative residual the backward's CG reaches (``linear_solver="pcg"``) whatever the
forward's ``PCG.rtol``: derivatives are as exact as the dtype allows."""


def _tangent_solve(graph: FactorGraph, options: dict[str, Any], xs: Variables,
                   rhs: Array) -> Array:
    """H⁻¹·rhs, H the exact Hessian at ``xs``, by the forward's linear solver: ``dense``
    Cholesky, ``pcg`` (block-Jacobi CG to :data:`BACKWARD_RTOL` on any backend),
    ``schur`` (the eliminated type's blocks eliminated as in the forward,
    :func:`_schur_solve`), else (``sparse``) the sparse direct solver. Each inside
    ``jax.lax.custom_linear_solve``, checked: a solve that fails raises."""
    st = graph.structure
    solver = options.get("linear_solver")
    method = solver.resolve(graph) if solver is not None else "sparse"
    if method == "schur":
        return _schur_solve(graph, xs, rhs, solver.dense_max)
    hess = exact_hessian_csr(graph, xs)
    idx, ptr = st.csr_indices, st.csr_indptr
    if method == "pcg":
        rtol = BACKWARD_RTOL.get(jnp.dtype(hess.dtype).name, 1e-10)
        inner = pcg_spd(block_jacobi(_diagonal_blocks(graph, hess)), rtol,
                        options["cg"].max_iters)
    else:
        direct = solve_dense if method == "dense" else solve_sparse_direct
        inner = lambda _, b: direct(hess, idx, ptr, b)  # noqa: E731
    return solve_sparse_spd(hess, idx, ptr, rhs,
                            checked(inner, _backward_failure(method, rhs.dtype)))


def _backward_failure(method: str, dtype: Any) -> str:
    """The error of a failed backward solve by ``method`` in ``dtype``: cause, remedies."""
    name = jnp.dtype(dtype).name
    why = ("CG did not reach its tolerance in PCG.max_iters iterations, or H is not "
           "positive definite" if method == "pcg" else
           f"H is not positive definite to {name} precision")
    fixes = ["tighten the stopping rule", "add priors on weakly determined variables"]
    fixes += ["raise PCG.max_iters"] if method == "pcg" else []
    fixes += ["differentiate in float64"] if name != "float64" else []
    return (f"graph.solve: cannot differentiate the solution: the {method!r} solve with the "
            f"exact Hessian H of the cost at the solution failed ({why}). Either the solve "
            f"stopped away from a strict minimum (check the solution's status and "
            f"iterations) or the problem is too ill-conditioned for {name} (down-weighted or "
            f"barely observed variables): {', '.join(fixes[:-1])} or {fixes[-1]}.")


def _schur_solve(graph: FactorGraph, xs: Variables, rhs: Array, dense_max: int) -> Array:
    """H⁻¹·rhs by Schur elimination (:func:`~jaxpose.graph._schur.schur_step` on the
    exact Hessian's :func:`_exact_schur_parts`, the reduced system solved like the
    forward's) inside ``jax.lax.custom_linear_solve``, whose operator is the exact
    Hessian-vector product (used only by higher derivatives)."""
    add = 1.0 - free_flat(graph, rhs.dtype)  # fixed variables: identity rows
    parts = _exact_schur_parts(graph, xs)
    zero = jnp.zeros((graph.structure.size,), rhs.dtype)

    def matvec(v: Array) -> Array:
        hvp = jax.jvp(jax.grad(partial(_chart_cost, graph, xs)), (zero,), (v,))[1]
        return hvp + add * v

    def inner(_: object, b: Array) -> Array:
        return schur_step(graph, parts, -b, add, reduced_solver(graph, dense_max))

    return jax.lax.custom_linear_solve(
        matvec, rhs, checked(inner, _backward_failure("schur", rhs.dtype)), symmetric=True)


def _exact_schur_parts(graph: FactorGraph, xs: Variables) -> SchurParts:
    """:class:`~jaxpose.graph._schur.SchurParts` of the exact Hessian at ``xs``, from the
    per-factor Hessians in chunks (:func:`_over_chunks`): U's and V's blocks are summed
    as they come, only the entries B (one (d_k, d_e) block per factor and kept slot) are
    kept per factor — the per-factor blocks of the whole graph at once cost 4x the
    forward solve's memory on a 10 000-observation BA problem."""
    dtype = jax.tree.leaves(xs)[0].dtype
    zero = 0.0 * jax.tree.leaves(xs)[0].reshape(-1)[0]  # see exact_hessian_csr

    def fill(n: int, acc: Any) -> Any:
        def add(acc: Any, hess: Any, take: Callable[[Any], Any], new: Array,
                start: Array) -> Any:  # overlapping chunks write the same B again
            return add_group(graph, n, acc, lambda s, t: hess[s][t], take, new, start)

        return _over_chunks(graph, n, xs, acc, add)

    return _schur_without_fixed(graph, schur_parts_by_group(graph, dtype, fill, zero))


def _schur_without_fixed(graph: FactorGraph, parts: SchurParts) -> SchurParts:
    """``parts`` with every block of a fixed variable zeroed (U's, V's and the entries B)."""
    st = graph.structure
    sc = st.schur
    free, e = st.free, sc.eliminated
    u = sc.pattern.without_fixed(parts.u, [free[k] for k in sc.kept])
    v = parts.v * free[e].astype(parts.v.dtype)[:, None, None]
    w = [b * (free[k][var] * free[e][point]).astype(b.dtype)[:, None, None]
         for b, k, var, point in zip(parts.w, sc.kept, sc.w_var, sc.w_point, strict=True)]
    return SchurParts(u, v, w)


def _diagonal_blocks(graph: FactorGraph, values: Array) -> tuple[Array, ...]:
    """Per variable type the (n, d, d) diagonal blocks of the CSR matrix ``values``. A
    diagonal block's columns are consecutive and all present in each of its rows, so
    entry (a, b) of block i sits ``b − a`` after the diagonal entry of row ``i·d + a``."""
    st = graph.structure
    out = []
    for off, n, d in zip(st.offsets[:-1], st.counts, st.dims, strict=True):
        rows = off + jnp.arange(n * d).reshape(n, d)
        shift = jnp.arange(d)[None, None, :] - jnp.arange(d)[None, :, None]
        out.append(values[st.diag_pos[rows][:, :, None] + shift])
    return tuple(out)


def solve_differentiable(run: Callable[..., Any], graph: FactorGraph, x0: Variables,
                         **options: Any) -> Any:
    """``run(graph, x0, **options)`` (a :class:`~jaxpose.graph.GraphSolution`) with the
    exact, any-order derivatives of the module docstring."""
    return _differentiable(graph, x0, run=run, options=options)


__all__ = ["exact_hessian_csr", "solve_differentiable"]
