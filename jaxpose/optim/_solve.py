"""``least_squares``: the one-call solver over pytrees of Lie groups and arrays."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp

from .._dtypes import inexact
from .._precision import full_precision
from . import _iterate
from ._correctors import Corrector
from ._implicit import ImplicitAdjoint, UnrolledAdjoint, implicit_solve
from ._problem import Problem, as_problem
from ._solution import Solution
from ._solver import INITIAL_NOT_FINITE, AbstractSolver, LevenbergMarquardt, SolverState
from ._stopping import StopOnPlateau, Stopping

PyTree = Any


def _to_solution(state: SolverState, history: bool) -> Solution:
    return Solution(
        params=state.best_params,
        status=state.status,
        num_steps=state.num_steps,
        num_accepted=state.num_accepted,
        cost=state.best_cost,
        initial_cost=state.initial_cost,
        grad_norm=jnp.max(jnp.abs(state.system.grad), initial=0.0),
        history=state.history if history else None,
    )


def _runner(
    solver: AbstractSolver, stopping: Stopping, *, verbose: bool, history: bool, unrolled: bool
) -> Callable[[Problem, PyTree, PyTree], Solution]:
    def run(problem: Problem, params: PyTree, args: PyTree) -> Solution:
        # the residuals are evaluated in the first trial only (it linearises at params);
        # their initial NaN/Inf check is attached to the solution instead
        state = solver._init(problem, params, args, stopping, history=history,
                             evaluate=False)

        def body(s: SolverState) -> SolverState:
            return solver._step(problem, s, args, stopping, verbose)

        def cond(s: SolverState) -> jax.Array:
            return ~s.done

        if stopping.budget > 0:
            if unrolled:
                # the first trial (it only linearises) runs before the loop: inside it,
                # its skipped solve would be a lax.cond whose predicate vmap batches, and
                # reverse mode then transposes lineax's solve on the zero residuals JAX
                # stores for an untaken branch (lineax raises on the singular system)
                state = eqxi.while_loop(
                    cond, body, body(state), max_steps=stopping.budget, kind="checkpointed"
                )
            else:
                state = jax.lax.while_loop(cond, body, state)
        else:  # no step: the first trial only linearises (status MAX_STEPS, or CONVERGED
            state = body(state)  # by gtol), so grad_norm and cost are those at params
        return _iterate.check_initial_cost(_to_solution(state, history), state.initial_cost,
                                           INITIAL_NOT_FINITE)

    return run


@eqx.filter_jit
@full_precision
def least_squares(
    residual_fn: Callable[[PyTree, PyTree], PyTree] | Problem,
    params: PyTree,
    args: PyTree = None,
    solver: AbstractSolver | None = None,
    *,
    weights: PyTree = None,
    kernel: PyTree = None,
    corrector: Corrector | None = None,
    max_steps: int = 100,
    cost_atol: float = 0.0,
    cost_rtol: float = 1e-10,
    gtol: float = 1e-10,
    xtol: float = 1e-10,
    max_rejects: int = 64,
    stop: StopOnPlateau | None = None,
    adjoint: str | ImplicitAdjoint | UnrolledAdjoint = "implicit",
    jacobian: str | Callable[..., jax.Array] = "auto",
    verbose: bool = False,
    history: bool = False,
) -> Solution:
    """Minimise ``0.5 · Σ_blocks ρ(rᵀ W r)`` with r = ``residual_fn(params, args)``.

    ``params`` is any pytree of :class:`~jaxpose.lie.LieGroup` elements (updated by the
    right retraction X·Exp(δ)) and arrays (updated by addition). The residual is any
    pytree of arrays; each leaf ``(*batch, d)`` is a set of d-dimensional blocks (see
    :class:`~jaxpose.optim.Problem` for ``weights``, ``kernel`` and ``jacobian``). The
    whole iteration is one ``lax.while_loop`` (a checkpointed one for
    ``adjoint="unrolled"``), so this function jits and vmaps; under ``vmap`` every
    problem keeps its own damping, acceptance and stopping.

    Compiled with ``eqx.filter_jit``: arrays (in ``params``, ``args``, ``weights``, array
    fields of kernels and solvers) are traced and everything else is static, so calling
    again with the *same* ``residual_fn`` object and new data of the same shapes reuses
    the compiled program (a new ``lambda`` per call compiles anew).

    Args:
        solver: :class:`LevenbergMarquardt` (default, TrustRegion strategy, Cholesky) or
            :class:`GaussNewton`.
        corrector: :class:`FastTriggs` (default when a kernel is given) or :class:`Triggs`.
        max_steps: iteration (trial step) budget.
        cost_atol, cost_rtol: an accepted step decreasing the cost by at most
            ``cost_atol + cost_rtol·cost`` ends the solve (converged).
        gtol: converged when the tangent gradient satisfies ‖g‖_∞ ≤ gtol.
        xtol: converged when a finite trial step has ‖δ‖₂ ≤ xtol.
        max_rejects: consecutive rejected trials before giving up (DIVERGED, or
            NON_FINITE when the trials were NaN/Inf); a rejection that cannot change the
            damping (Constant, clamped damping, Gauss-Newton) gives up at once.
        stop: optional :class:`StopOnPlateau` rule.
        adjoint: ``"implicit"`` (implicit function theorem, one linear solve in the
            backward pass; see :mod:`jaxpose.optim._implicit`) or ``"unrolled"``
            (autodiff through the iterations); or an :class:`ImplicitAdjoint` instance.
        verbose: print one line per iteration from inside jit.
        history: record the cost after every iteration in ``Solution.history``.

    Returns:
        :class:`Solution` with the best ``params``, ``status``, ``num_steps``, costs.

    Raises:
        ValueError: at trace time for malformed weights, kernels or options (shapes), or
            a ``residual_fn`` returning no residuals.
        TypeError: at trace time for arguments of the wrong type (solver, adjoint, ...).
        RuntimeError: (``eqx.EquinoxRuntimeError``, from ``eqx.error_if``) if
            ``residual_fn`` is NaN/Inf at the initial ``params``. A Jacobian that is not
            finite there (e.g. ``sqrt(x)`` at 0) does not raise: solvers report a status,
            so the solve ends at once with ``NON_FINITE`` and the initial ``params``
            (as :func:`jaxpose.graph.solve` does). Also if a traced kernel parameter
            is outside its domain (e.g. ``Huber(d)`` with ``d ≤ 0``).
    """
    params = inexact(params)
    solver = LevenbergMarquardt() if solver is None else solver
    if not isinstance(solver, AbstractSolver):
        raise TypeError(
            f"solver: expected GaussNewton or LevenbergMarquardt, got {type(solver).__name__}"
        )
    problem = as_problem(
        residual_fn, weights=weights, kernel=kernel, corrector=corrector, jacobian=jacobian
    )
    stopping = Stopping(
        max_steps=max_steps,
        cost_atol=cost_atol,
        cost_rtol=cost_rtol,
        gtol=gtol,
        xtol=xtol,
        max_rejects=max_rejects,
        plateau=stop,
    )
    if isinstance(adjoint, str):
        if adjoint not in ("implicit", "unrolled"):
            raise ValueError(f"adjoint={adjoint!r}: expected 'implicit' or 'unrolled'")
        adjoint = ImplicitAdjoint() if adjoint == "implicit" else UnrolledAdjoint()
    if not isinstance(adjoint, (ImplicitAdjoint, UnrolledAdjoint)):
        raise TypeError(
            f"adjoint: expected 'implicit', 'unrolled' or ImplicitAdjoint, got "
            f"{type(adjoint).__name__}"
        )
    problem.check(params, args)
    problem = problem._with_checked_kernels()._resolve(params, args)
    unrolled = isinstance(adjoint, UnrolledAdjoint)
    run = _runner(solver, stopping, verbose=verbose, history=history, unrolled=unrolled)
    if unrolled:
        return run(problem, params, args)
    return implicit_solve(run, problem, params, args, adjoint)


__all__ = ["least_squares"]
