"""Levenberg–Marquardt on factor graphs (sparse path), one ``lax.while_loop``.

Each iteration solves the damped normal equations (H + λ·D) δ = −g and evaluates the cost
at X ⊕ δ. Damping D: ``"identity"`` (λ·I, GTSAM's default) or ``"diagonal"`` (Marquardt
scaling, D = diag(H) clamped to [1e-6, 1e32], as Ceres and GTSAM's ``diagonalDamping``).
A step is accepted when it lowers the cost; the gain ratio
ρ = (F(x) − F(x ⊕ δ)) / (L(0) − L(δ)) drives λ: with ``lambda_factor`` f (GTSAM's rule)
λ ← λ/f on success and λ·f on failure; with ``lambda_factor=None`` Nielsen's rule
(λ·max(1/3, 1 − (2ρ − 1)³) on success, λ·ν with ν doubling on failure). The loop only
ever moves to an accepted (lower-cost) point, so the returned estimate is the best seen.

Stopping: an accepted step lowering the cost by at most ``rtol``·cost or ``atol``; a
model decrease L(0) − L(δ) at the cost's floating-point resolution (16·eps·cost: nothing
measurable is left, whether the step was accepted or not); ‖g‖∞ ≤ ``gtol``; ``max_steps``
linear solves; λ beyond ``lambda_max`` (stalled).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from . import linear
from .problem import (
    FactorGraph,
    Variables,
    block_diagonal,
    csr_values,
    gradient,
    hessian_vector,
    linearize,
    retract_all,
)
from .schur import schur_step

Array = jax.Array

CONVERGED, MAX_STEPS, STALLED, NON_FINITE = 0, 1, 2, 3
STATUS_NAMES = {
    CONVERGED: "converged",
    MAX_STEPS: "max_steps",
    STALLED: "stalled",
    NON_FINITE: "non_finite",
}
LINEAR_SOLVERS = ("auto", "sparse", "pcg", "dense", "schur")
DENSE_MAX = 600  # "auto": dense Cholesky up to this many tangent dimensions


class GraphSolution(eqx.Module):
    """Result of :func:`solve`.

    ``status``: 0 converged, 1 max_steps, 2 stalled (damping exhausted; the estimate is
    the best found), 3 non_finite (a non-finite cost or step appeared; best estimate kept).
    ``iterations``: linear solves (accepted and rejected trials).
    ``history``: cost after each iteration (NaN beyond ``iterations``)."""

    variables: Variables
    cost: Array
    initial_cost: Array
    iterations: Array
    status: Array
    history: Array
    linear_iterations: Array

    @property
    def status_name(self) -> str:
        return STATUS_NAMES[int(self.status)]


def default_rtol(dtype: Any) -> float:
    """1e-10 in float64; 1e-6 (about 8 eps) in float32."""
    return 1e-10 if jnp.finfo(dtype).bits >= 64 else 1e-6


def solve(
    graph: FactorGraph,
    variables: Variables | None = None,
    *,
    linear_solver: str = "auto",
    max_steps: int = 100,
    rtol: float | None = None,
    atol: float = 0.0,
    gtol: float = 0.0,
    damping: str = "identity",
    lambda_init: float = 1e-5,
    lambda_factor: float | None = 10.0,
    lambda_min: float = 1e-15,
    lambda_max: float = 1e16,
    cg_rtol: float = 1e-8,
    cg_max_iters: int = 2000,
    verbose: bool = False,
) -> GraphSolution:
    """Minimise ``0.5·Σ ρ(rᵀΩr)`` over the graph's variables with Levenberg–Marquardt.

    Args:
        graph: the :class:`FactorGraph` (its ``variables`` are the default start).
        variables: optional starting values with the same structure.
        linear_solver: ``"sparse"`` (sparse Cholesky, CHOLMOD on the host through a
            callback; its symbolic analysis is reused across iterations), ``"pcg"``
            (block-Jacobi preconditioned CG, any backend), ``"dense"`` (Cholesky, small
            problems), ``"schur"`` (eliminate the graph's ``eliminate`` variable type, then
            a dense or sparse Cholesky of the reduced system) or ``"auto"`` (schur when the
            graph eliminates a type, else dense up to 600 tangent dimensions, else sparse).
        max_steps: maximum LM iterations (linear solves, accepted or rejected).
        rtol, atol: stop when an accepted step lowers the cost by less than
            ``rtol·cost`` or ``atol``; ``rtol=None``: :func:`default_rtol` of the dtype.
        gtol: stop when ‖g‖∞ ≤ gtol.
        damping: ``"identity"`` (λ·I) or ``"diagonal"`` (λ·diag(H), Marquardt).
        lambda_init, lambda_factor, lambda_min, lambda_max: damping schedule (module
            docstring); ``lambda_factor=None`` selects Nielsen's rule.
        cg_rtol, cg_max_iters: inner tolerance and budget of ``"pcg"``.
        verbose: print one line per iteration from inside jit.
    """
    if linear_solver not in LINEAR_SOLVERS:
        raise ValueError(
            f"solve(linear_solver={linear_solver!r}): expected one of {LINEAR_SOLVERS}"
        )
    if damping not in ("identity", "diagonal"):
        raise ValueError(f"solve(damping={damping!r}): expected 'identity' or 'diagonal'")
    if lambda_factor is not None and not lambda_factor > 1.0:
        raise ValueError(f"solve(lambda_factor={lambda_factor!r}): expected a float > 1 or None")
    st = graph.structure
    if linear_solver == "schur" and st.schur is None:
        raise ValueError(
            "solve(linear_solver='schur'): the graph eliminates no variable type; build it "
            "with FactorGraph(..., eliminate=TYPE_NAME)"
        )
    if linear_solver == "auto":
        linear_solver = ("schur" if st.schur is not None
                         else "dense" if graph.size <= DENSE_MAX else "sparse")
    x0 = graph.variables if variables is None else variables
    lin0 = linearize(graph, x0)
    dtype = lin0.cost.dtype
    rtol = default_rtol(dtype) if rtol is None else rtol
    eps = jnp.finfo(dtype).eps
    free_flat = jnp.concatenate(
        [jnp.repeat(f, d) for f, d in zip(st.free, st.dims, strict=True)]
    ).astype(dtype)
    lin0 = eqx.error_if(
        lin0,
        ~jnp.isfinite(lin0.cost),
        "solve: the cost is not finite at the initial variables (check measurements, "
        "information matrices and initial values)",
    )

    def scale(diag, lam):
        if damping == "identity":
            return lam * jnp.ones_like(diag)
        return lam * jnp.clip(diag, 1e-6, 1e32)

    def solve_step(lin, g, lam):
        if linear_solver == "pcg":
            blocks = block_diagonal(graph, lin)
            damped = tuple(
                b
                + jax.vmap(jnp.diag)(
                    scale(jax.vmap(jnp.diag)(b), lam)
                    + 1.0 - jnp.repeat(f[:, None], b.shape[-1], 1).astype(dtype)
                )
                for b, f in zip(blocks, st.free, strict=True)
            )
            diag = jnp.concatenate([jax.vmap(jnp.diag)(b).reshape(-1) for b in blocks])
            dvec = scale(diag, lam)

            def matvec(v):
                return hessian_vector(graph, lin, v) + dvec * v + (1.0 - free_flat) * v

            return linear.solve_pcg(
                matvec, -g, linear.block_jacobi(damped), rtol=cg_rtol, max_iters=cg_max_iters
            )
        if linear_solver == "schur":
            reduced = st.schur.pattern.size
            direct = linear.solve_dense if reduced <= DENSE_MAX else linear.solve_sparse_direct
            return schur_step(graph, lin, g, lambda d: scale(d, lam), direct), jnp.asarray(0)
        data = csr_values(graph, lin)
        diag = data[st.diag_pos]
        data = data.at[st.diag_pos].add(scale(diag, lam) + (1.0 - free_flat))
        solver = linear.solve_sparse_direct if linear_solver == "sparse" else linear.solve_dense
        return solver(data, st.csr_indices, st.csr_indptr, -g), jnp.asarray(0)

    def cond(state):
        return state["status"] < 0

    def body(state):
        x, lin, g = state["x"], state["lin"], state["g"]
        lam, nu, k = state["lam"], state["nu"], state["k"]
        step, its = solve_step(lin, g, lam)
        step = step * free_flat
        x_new = retract_all(graph, x, step)
        lin_new = linearize(graph, x_new)
        hstep = hessian_vector(graph, lin, step)
        predicted = -(jnp.vdot(g, step) + 0.5 * jnp.vdot(step, hstep))
        actual = lin.cost - lin_new.cost
        finite = jnp.isfinite(lin_new.cost) & jnp.all(jnp.isfinite(step))
        rho = actual / jnp.where(predicted > 0, predicted, 1.0)
        accept = finite & (predicted > 0) & (actual > 0)
        if lambda_factor is None:  # Nielsen
            lam_acc = lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            lam_rej = jnp.maximum(lam, lambda_min) * nu
            new_nu = jnp.where(accept, 2.0, nu * 2.0)
        else:
            lam_acc = lam / lambda_factor
            lam_rej = jnp.maximum(lam, lambda_min) * lambda_factor
            new_nu = nu
        new_lam = jnp.where(accept, jnp.maximum(lam_acc, lambda_min), lam_rej)
        pick = lambda a, b: jax.tree.map(lambda u, v: jnp.where(accept, u, v), a, b)  # noqa: E731
        x_next = pick(x_new, x)
        lin_next = pick(lin_new, lin)
        g_next = jnp.where(accept, gradient(graph, lin_new), g)
        small_decrease = accept & ((actual <= rtol * lin.cost) | (actual <= atol))
        at_resolution = finite & (predicted <= 16 * eps * jnp.abs(lin.cost))
        small_grad = jnp.max(jnp.abs(g_next)) <= gtol
        status = jnp.where(
            ~jnp.isfinite(lin_new.cost) & (new_lam >= lambda_max),
            NON_FINITE,
            jnp.where(
                small_decrease | at_resolution | small_grad,
                CONVERGED,
                jnp.where(
                    new_lam >= lambda_max, STALLED, jnp.where(k + 1 >= max_steps, MAX_STEPS, -1)
                ),
            ),
        )
        if verbose:
            jax.debug.print(
                "iter {k:4d}  cost {c:.6e}  gain {r:+.2e}  lambda {l:.1e}  |step| {s:.2e}  "
                "accepted {a}  cg {i}",
                k=k,
                c=lin_next.cost,
                r=rho,
                l=lam,
                s=jnp.linalg.norm(step),
                a=accept,
                i=its,
            )
        hist = state["history"].at[k].set(lin_next.cost)
        return dict(
            x=x_next,
            lin=lin_next,
            g=g_next,
            lam=new_lam,
            nu=new_nu,
            k=k + 1,
            status=status,
            history=hist,
            cg=state["cg"] + its,
        )

    init = dict(
        x=x0,
        lin=lin0,
        g=gradient(graph, lin0),
        lam=jnp.asarray(lambda_init, dtype),
        nu=jnp.asarray(2.0, dtype),
        k=jnp.asarray(0),
        status=jnp.asarray(-1),
        history=jnp.full((max_steps,), jnp.nan, dtype),
        cg=jnp.asarray(0),
    )
    init["status"] = jnp.where(
        (jnp.max(jnp.abs(init["g"])) <= gtol) | (max_steps == 0), CONVERGED, -1
    )
    out = jax.lax.while_loop(cond, body, init)
    return GraphSolution(
        variables=out["x"],
        cost=out["lin"].cost,
        initial_cost=lin0.cost,
        iterations=out["k"],
        status=out["status"],
        history=out["history"],
        linear_iterations=out["cg"],
    )


def summary(sol: GraphSolution) -> dict[str, Any]:
    """Plain-Python summary of a solution."""
    return {
        "status": sol.status_name,
        "iterations": int(sol.iterations),
        "initial_cost": float(sol.initial_cost),
        "final_cost": float(sol.cost),
    }
