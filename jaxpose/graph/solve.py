"""Levenberg–Marquardt on factor graphs (sparse path), one ``lax.while_loop``.

The pieces are those of :mod:`jaxpose.optim`: a damping :class:`~jaxpose.optim.Strategy`
(default :class:`~jaxpose.graph.strategies.LambdaFactor`, GTSAM's rule, or Nielsen's rule
with ``lambda_factor=None``; :class:`~jaxpose.optim.Constant`, ``Adaptive``,
``TrustRegion`` and ``Dogleg`` work too), robust kernels and correctors per factor
(:class:`~jaxpose.graph.Factor`), :class:`~jaxpose.optim.Stopping` tolerances and
:class:`~jaxpose.Results` codes. Only the linear algebra is sparse: each trial solves
``(H + diag(lift) + λ·diag(D)) δ = −g`` with H = J̃ᵀJ̃ block-sparse, D = 1 (``damping=
"identity"``, GTSAM's default) or D = clamp(diag H, 1e-6, 1e32) (``"diagonal"``, Marquardt,
as Ceres and GTSAM's ``diagonalDamping``), then evaluates the cost at X ⊕ δ. One
iteration is one trial: a finite trial that lowers the cost is accepted (gain ratio
ρ = (F(x) − F(x ⊕ δ)) / (L(0) − L(δ)) > 0), otherwise only the damping changes. The loop
only ever moves to an accepted (lower-cost) point, so the returned estimate is the best
seen.

Stopping (:func:`jaxpose.optim.stopping.check`): an accepted step lowering the cost by at
most ``atol + rtol·cost``; ‖g‖∞ ≤ ``gtol``; ‖δ‖ ≤ ``xtol``; a rejected trial whose
predicted decrease is at the cost's floating-point resolution; ``max_steps`` trials; a
rejection that cannot change the damping (λ at its bound: ``Results.DIVERGED``, "stalled",
best estimate kept).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from ..optim.stopping import Stopping, Trial, check, nonfinite_run, plateau_count
from ..optim.strategies import NormalEquations, Strategy
from ..results import Results
from . import linear
from .problem import (
    FactorGraph,
    Variables,
    block_diagonal,
    csr_values,
    gradient,
    hessian_diagonal,
    hessian_vector,
    linearize,
    retract_all,
    split,
)
from .schur import schur_step
from .strategies import LambdaFactor, Nielsen

Array = jax.Array

LINEAR_SOLVERS = ("auto", "sparse", "pcg", "dense", "schur")
DENSE_MAX = 600  # "auto": dense Cholesky up to this many tangent dimensions


class GraphSolution(eqx.Module):
    """Result of :func:`solve`.

    ``status``: a :class:`jaxpose.Results` code: 0 converged, 1 max_steps,
    2 diverged (stalled: damping exhausted; the estimate is the best found),
    3 non_finite (a non-finite cost or step stopped the solve: ``max_rejects`` such
    trials, or the budget ran out while every trial since the last accepted one was
    non-finite, or the gradient at the start is not finite; best estimate kept).
    ``iterations``: linear solves (accepted and rejected trials).
    ``history``: cost after each iteration (NaN beyond ``iterations``).
    ``linear_iterations``: total CG iterations (``"pcg"``; 0 for direct solvers)."""

    variables: Variables
    cost: Array
    initial_cost: Array
    iterations: Array
    status: Array
    history: Array
    linear_iterations: Array

    @property
    def status_name(self) -> str:
        """``status`` as text: converged, max_steps, diverged or non_finite
        (:meth:`jaxpose.Results.name_of`; an array of names for a batched solution)."""
        return Results.name_of(self.status)


def default_rtol(dtype: Any) -> float:
    """1e-10 in float64; 1e-6 (about 8 eps) in float32."""
    return 1e-10 if jnp.finfo(dtype).bits >= 64 else 1e-6


class _Hessian:
    """H = J̃ᵀJ̃ as an operator (``H @ v``) for the strategies' step rules."""

    def __init__(self, graph: FactorGraph, lin: Any):
        self.graph, self.lin = graph, lin

    def __matmul__(self, v: Array) -> Array:
        return hessian_vector(self.graph, self.lin, v)


class _SparseLinear:
    """The ``solve(jac, res, hess, grad, diag_add)`` protocol of the optim linear solvers
    on the sparse path: solves ``(H + diag(diag_add)) δ = −grad`` with H from the
    linearisation (fixed variables get an identity row). Records CG iterations."""

    def __init__(self, kind: str, graph: FactorGraph, lin: Any, free: Array,
                 cg_rtol: Any, cg_max_iters: int):
        self.kind, self.graph, self.lin, self.free = kind, graph, lin, free
        self.cg_rtol, self.cg_max_iters = cg_rtol, cg_max_iters
        self.iterations = jnp.asarray(0)

    def solve(self, jac: Any, res: Any, hess: Any, grad: Array, diag_add: Array) -> Array:
        graph, lin, st = self.graph, self.lin, self.graph.structure
        add = diag_add + (1.0 - self.free)
        if self.kind == "pcg":
            blocks = block_diagonal(graph, lin)
            damped = tuple(b + jax.vmap(jnp.diag)(a) for b, a in
                           zip(blocks, split(graph, add), strict=True))
            x, its = linear.solve_pcg(
                lambda v: hessian_vector(graph, lin, v) + add * v, -grad,
                linear.block_jacobi(damped), rtol=self.cg_rtol, max_iters=self.cg_max_iters,
            )
            self.iterations = self.iterations + its
            return x
        if self.kind == "schur":
            # the reduced system: CHOLMOD on CPU (single-threaded reference BLAS: the
            # dense LAPACK Cholesky goes through a multi-threaded OpenBLAS whose spinning
            # threads cost up to 100x on a loaded machine); dense Cholesky on
            # accelerators when it is small
            small = st.schur.pattern.size <= DENSE_MAX and jax.default_backend() != "cpu"
            direct = linear.solve_dense if small else linear.solve_sparse_direct
            return schur_step(graph, lin, grad, add, direct)
        data = csr_values(graph, lin).at[st.diag_pos].add(add)
        direct = linear.solve_sparse_direct if self.kind == "sparse" else linear.solve_dense
        return direct(data, st.csr_indices, st.csr_indptr, -grad)


def _default_strategy(lambda_init: float, lambda_factor: float | None, lambda_min: float,
                      lambda_max: float) -> Strategy:
    if lambda_factor is None:
        return Nielsen(lambda_init, lambda_min, lambda_max)
    if not lambda_factor > 1.0:
        raise ValueError(f"solve(lambda_factor={lambda_factor!r}): expected a float > 1 or None")
    return LambdaFactor(lambda_init, lambda_factor, lambda_min, lambda_max)


@eqx.filter_jit
def solve(
    graph: FactorGraph,
    variables: Variables | None = None,
    *,
    linear_solver: str = "auto",
    max_steps: int = 100,
    rtol: float | None = None,
    atol: float = 0.0,
    gtol: float = 0.0,
    xtol: float = 0.0,
    damping: str = "identity",
    lambda_init: float = 1e-5,
    lambda_factor: float | None = 10.0,
    lambda_min: float = 1e-15,
    lambda_max: float = 1e16,
    strategy: Strategy | None = None,
    stopping: Stopping | None = None,
    cg_rtol: float | str = 1e-8,
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
            a sparse Cholesky of the reduced system; dense on accelerators when it has at
            most 600 dimensions) or ``"auto"`` (schur when the
            graph eliminates a type, else dense up to 600 tangent dimensions, else sparse).
        max_steps: maximum LM iterations (linear solves, accepted or rejected).
        rtol, atol: stop when an accepted step lowers the cost by at most
            ``atol + rtol·cost``; ``rtol=None``: :func:`default_rtol` of the dtype.
        gtol: stop when ‖g‖∞ ≤ gtol.  xtol: stop when a finite step has ‖δ‖ ≤ xtol.
        damping: ``"identity"`` (λ·I) or ``"diagonal"`` (λ·diag(H), Marquardt).
        lambda_init, lambda_factor, lambda_min, lambda_max: the default damping schedule:
            :class:`~jaxpose.graph.strategies.LambdaFactor` (GTSAM), or
            :class:`~jaxpose.graph.strategies.Nielsen` with ``lambda_factor=None``.
        strategy: any :class:`jaxpose.optim.Strategy` instead (``Constant``, ``Adaptive``,
            ``TrustRegion``, ``Dogleg``, ``LambdaFactor``, ``Nielsen``).
        stopping: a :class:`jaxpose.optim.Stopping` instead of ``max_steps``/``rtol``/
            ``atol``/``gtol``/``xtol`` (e.g. with a ``StopOnPlateau`` rule).
        cg_rtol, cg_max_iters: inner tolerance and budget of ``"pcg"``; ``cg_rtol=
            "inexact"`` uses the inexact-Newton forcing sequence
            η = min(0.1, √(‖g‖/‖g₀‖)) (Eisenstat–Walker style).
        verbose: print one line per iteration from inside jit.

    Compiled with ``eqx.filter_jit``: the graph's arrays (variables, measurements,
    information, weights) are traced and its structure and the options are static, so a
    repeated call on a graph of the same structure with new values reuses the program.
    """
    if linear_solver not in LINEAR_SOLVERS:
        raise ValueError(
            f"solve(linear_solver={linear_solver!r}): expected one of {LINEAR_SOLVERS}"
        )
    if damping not in ("identity", "diagonal"):
        raise ValueError(f"solve(damping={damping!r}): expected 'identity' or 'diagonal'")
    if strategy is None:
        strategy = _default_strategy(lambda_init, lambda_factor, lambda_min, lambda_max)
    elif not isinstance(strategy, Strategy):
        raise TypeError(
            f"solve(strategy): expected a jaxpose.optim Strategy, got {type(strategy).__name__}"
        )
    if stopping is not None and not isinstance(stopping, Stopping):
        raise TypeError(
            f"solve(stopping): expected a jaxpose.optim Stopping, got {type(stopping).__name__}"
        )
    if isinstance(cg_rtol, str) and cg_rtol != "inexact":
        raise ValueError(f"solve(cg_rtol={cg_rtol!r}): expected a float or 'inexact'")
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
    if stopping is None:
        stopping = Stopping(
            max_steps=max_steps, cost_atol=atol,
            cost_rtol=default_rtol(dtype) if rtol is None else rtol, gtol=gtol, xtol=xtol,
        )
    free_flat = jnp.concatenate(
        [jnp.repeat(f, d) for f, d in zip(st.free, st.dims, strict=True)]
    ).astype(dtype)
    lin0 = eqx.error_if(
        lin0,
        ~jnp.isfinite(lin0.cost),
        "solve: the cost is not finite at the initial variables (check measurements, "
        "information matrices and initial values)",
    )
    g0 = gradient(graph, lin0)
    g0_norm = jnp.linalg.norm(g0)

    def body(state):
        x, lin, g, sstate, k = state["x"], state["lin"], state["g"], state["s"], state["k"]
        if damping == "identity":
            scale = jnp.ones_like(g)
        else:
            scale = jnp.clip(hessian_diagonal(graph, lin), 1e-6, 1e32)
        system = NormalEquations(None, None, _Hessian(graph, lin), g, scale, jnp.zeros_like(g))
        if cg_rtol == "inexact":
            eta = jnp.minimum(0.1, jnp.sqrt(jnp.linalg.norm(g) / jnp.maximum(g0_norm, 1e-300)))
        else:
            eta = cg_rtol
        solver = _SparseLinear(linear_solver, graph, lin, free_flat, eta, cg_max_iters)
        step = strategy.step(sstate, system, solver) * free_flat
        step_ok = jnp.all(jnp.isfinite(step))
        step = jnp.where(step_ok, step, 0.0)
        x_new = retract_all(graph, x, step)
        lin_new = linearize(graph, x_new)
        predicted = -(jnp.vdot(g, step) + 0.5 * jnp.vdot(step, hessian_vector(graph, lin, step)))
        actual = lin.cost - lin_new.cost
        finite = step_ok & jnp.isfinite(lin_new.cost)
        tiny = jnp.finfo(dtype).tiny
        rho = jnp.where(predicted > tiny, actual / jnp.where(predicted > tiny, predicted, 1.0),
                        jnp.where(actual > 0, 1.0, -jnp.inf))
        rho = jnp.where(finite, rho, -jnp.inf)
        accept = finite & (actual > 0) & (rho > 0)
        new_s = strategy.update(sstate, rho, jnp.linalg.norm(step))
        pick = lambda a, b: jax.tree.map(lambda u, v: jnp.where(accept, u, v), a, b)  # noqa: E731
        x_next = pick(x_new, x)
        lin_next = pick(lin_new, lin)
        g_next = jnp.where(accept, gradient(graph, lin_new), g)
        rejects = jnp.where(accept, 0, state["rejects"] + 1).astype(jnp.int32)
        # a rejection that cannot change the damping would repeat the same trial
        stuck = ~accept & (strategy.damping(new_s) == strategy.damping(sstate))
        rejects = jnp.where(stuck, jnp.maximum(rejects, stopping.max_rejects), rejects)
        bad_run = nonfinite_run(state["bad_run"], accept, finite)
        plateau = plateau_count(stopping, lin.cost, lin_next.cost,
                                state["plateau"]).astype(jnp.int32)
        _, status = check(stopping, Trial(
            step=k + 1, last=lin.cost, cost=lin_next.cost, accepted=accept, finite=finite,
            step_norm=jnp.linalg.norm(step), predicted=predicted, initial=lin0.cost,
            grad_inf=jnp.max(jnp.abs(g_next), initial=0.0), rejects=rejects,
            plateau_count=plateau, nonfinite_run=~accept & bad_run,
        ))
        if verbose:
            jax.debug.print(
                "iter {k:4d}  cost {c:.6e}  gain {r:+.2e}  lambda {l:.1e}  |step| {s:.2e}  "
                "accepted {a}  cg {i}",
                k=k, c=lin_next.cost, r=rho, l=strategy.damping(sstate),
                s=jnp.linalg.norm(step), a=accept, i=solver.iterations,
            )
        hist = state["history"]
        if hist.shape[0]:
            hist = hist.at[jnp.minimum(k, hist.shape[0] - 1)].set(lin_next.cost)
        return dict(x=x_next, lin=lin_next, g=g_next, s=new_s, k=k + 1, status=status,
                    history=hist, cg=state["cg"] + jnp.asarray(solver.iterations, jnp.int32),
                    rejects=rejects, bad_run=bad_run,
                    plateau=plateau)

    # a Jacobian that is not finite at the start: no step can be computed (as in
    # jaxpose.optim.least_squares, a status rather than an exception)
    status0 = jnp.where(
        ~jnp.all(jnp.isfinite(g0)), Results.NON_FINITE,
        jnp.where(jnp.max(jnp.abs(g0), initial=0.0) <= stopping.gtol, Results.CONVERGED,
                  jnp.where(stopping.budget <= 0, Results.MAX_STEPS, Results.RUNNING)),
    ).astype(jnp.int32)
    init = dict(
        x=x0, lin=lin0, g=g0, s=strategy.init(dtype), k=jnp.asarray(0, jnp.int32),
        status=status0, history=jnp.full((stopping.budget,), jnp.nan, dtype),
        cg=jnp.asarray(0, jnp.int32), rejects=jnp.asarray(0, jnp.int32),
        bad_run=jnp.asarray(True), plateau=jnp.asarray(0, jnp.int32),
    )
    out = jax.lax.while_loop(lambda s: s["status"] < 0, body, init)
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
