"""The one trust-region / Levenberg–Marquardt iteration behind every least-squares solver.

:func:`trial` is one iteration: propose δ from the linearisation at the current estimate,
retract X ⊕ δ, linearise there, compute the gain ratio, accept or reject, track the best
estimate, update the damping rule and evaluate :func:`~jaxpose.optim._stopping.check`.
It is shared by the dense solvers of :mod:`jaxpose.optim` (``least_squares``,
``LevenbergMarquardt``, ``GaussNewton``) and by :func:`jaxpose.graph.solve` (block-sparse
linearisation). The two differ only in a small :class:`Path` (linearise, the Gauss–Newton
system as an operator, the damped linear solve, retract) and in the damping/acceptance
:class:`Rule` (a ``GaussNewton`` or ``LevenbergMarquardt`` module).
"""

from __future__ import annotations

from typing import Any, Protocol

import equinox as eqx
import jax
import jax.numpy as jnp

from ..results import Results
from ._stopping import Stopping, Trial, check, nonfinite_run, plateau_count
from ._strategies import NormalEquations

Array = jax.Array
PyTree = Any


class SolverState(eqx.Module):
    """Per-problem iteration state (all leaves are arrays; vmap-friendly)."""

    params: PyTree  # current estimate (last accepted)
    best_params: PyTree  # lowest-cost estimate seen
    cost: Array
    best_cost: Array
    initial_cost: Array
    system: Any  # linearisation at ``params`` (the path's form: NormalEquations when dense)
    strategy_state: Any
    num_steps: Array  # int32, trials so far
    num_accepted: Array  # int32
    rejects: Array  # int32, consecutive rejected trials
    bad_run: Array  # bool, every trial since the last accepted one was not finite
    plateau: Array  # int32, StopOnPlateau counter
    ratio: Array  # gain ratio of the last trial
    step_norm: Array  # ‖δ‖ of the last trial
    accepted: Array  # bool, last trial accepted
    linearized: Array  # bool, the first step (linearisation only) has run
    done: Array  # bool
    status: Array  # int32 Results code
    history: Array  # (budget + 1,) costs (index 0: the start), or (0,) when not recorded
    linear_iterations: Array  # int32, inner iterations of iterative linear solves


class Path(Protocol):
    """What one least-squares formulation supplies to :func:`trial`."""

    def linearize(self, params: PyTree) -> tuple[Any, Array, Array]:
        """(system, cost, finite) at ``params``: the carried linearisation (any pytree of
        arrays; zeros where not finite), the cost and whether it is usable."""

    def normal(self, system: Any) -> NormalEquations:
        """The Gauss–Newton system of ``system``: ``hess`` supports ``hess @ v``."""

    def propose(self, rule: Rule, sstate: Any, system: Any,
                normal: NormalEquations) -> tuple[Array, Array]:
        """(δ (n,), inner linear iterations) for the rule's damped system (``normal`` is
        :meth:`normal` of ``system``)."""

    def retract(self, params: PyTree, delta: Array) -> PyTree:
        """X ⊕ δ for a flat tangent δ (n,)."""


class Rule(Protocol):
    """The damping / acceptance hooks of a solver (``GaussNewton``, ``LevenbergMarquardt``)."""

    def _strategy_init(self, dtype: Any) -> Any: ...

    def _damping(self, sstate: Any) -> Array: ...

    def _strategy_update(self, sstate: Any, ratio: Array, step_norm: Array) -> Any: ...

    def _accept(self, finite: Array, actual: Array, ratio: Array) -> Array: ...

    def _on_failure_rejects(self, rejects: Array, finite: Array,
                            stopping: Stopping) -> Array: ...

    def _propose(self, sstate: Any, system: NormalEquations, linear_solver: Any) -> Array: ...


def select(pred: Array, a: PyTree, b: PyTree) -> PyTree:
    """``a`` where ``pred`` else ``b``, leaf by leaf."""
    return jax.tree.map(lambda x, y: jnp.where(pred, x, y), a, b)


def start_status(finite: Array, grad_inf: Array, stopping: Stopping) -> Array:
    """Status after the linearisation at the start: only a non-finite linearisation,
    ``gtol`` or a zero budget stop it."""
    return jnp.where(
        ~finite,
        Results.NON_FINITE,
        jnp.where(
            grad_inf <= stopping.gtol,
            Results.CONVERGED,
            jnp.where(stopping.budget <= 0, Results.MAX_STEPS, Results.RUNNING),
        ),
    ).astype(jnp.int32)


def check_initial_cost(solution: Any, initial_cost: Array, message: str) -> Any:
    """``solution`` (a pytree) with ``message`` raised (``eqx.error_if``) where the
    initial cost is not finite, attached to every array leaf, so a caller keeping any one
    of them alone (the status, a step count) still gets it: XLA drops a check nothing
    uses."""
    return eqx.error_if(solution, ~jnp.isfinite(initial_cost), message)


def init(rule: Rule, params: PyTree, system: Any, cost: Array, stopping: Stopping, *,
         history: bool, status: Array | None = None) -> SolverState:
    """Initial state at ``params`` with cost ``cost``.

    ``status=None``: ``system`` is a placeholder of the right layout and the first
    :func:`trial` only linearises (it does not count as an iteration) and sets the costs
    from that linearisation (``cost`` may then be a placeholder of its dtype). Otherwise
    ``system`` is the linearisation at ``params`` and ``status`` its :func:`start_status`.
    """
    dtype = cost.dtype
    hist = jnp.full((stopping.budget + 1,) if history else (0,), jnp.nan, dtype)
    if history:
        hist = hist.at[0].set(cost)
    zero_i = jnp.zeros((), jnp.int32)
    linearized = status is not None
    status = jnp.asarray(Results.RUNNING, jnp.int32) if status is None else status
    return SolverState(
        params=params,
        best_params=params,
        cost=cost,
        best_cost=cost,
        initial_cost=cost,
        system=system,
        strategy_state=rule._strategy_init(dtype),
        num_steps=zero_i,
        num_accepted=zero_i,
        rejects=zero_i,
        bad_run=jnp.asarray(True),
        plateau=zero_i,
        ratio=jnp.zeros((), dtype),
        step_norm=jnp.zeros((), dtype),
        accepted=jnp.asarray(False),
        linearized=jnp.asarray(linearized),
        done=status != Results.RUNNING,
        status=status,
        history=hist,
        linear_iterations=zero_i,
    )


def _print(label: str, fresh: Array, step: Array, cost: Array, ratio: Array, damping: Array,
           step_norm: Array, accepted: Array, grad_inf: Array, cg: Array) -> None:
    """One verbose line from inside jit: the start (linearisation: cost and ‖g‖∞) or a
    trial (cost, gain ratio, damping, ‖δ‖, accepted, inner linear iterations)."""

    def first() -> None:
        jax.debug.print(label + " start      cost {c:.6e}  |grad|inf {g:.3e}",
                        c=cost, g=grad_inf)

    def trial_line() -> None:
        jax.debug.print(
            label + " iter {i:4d}  cost {c:.6e}  ratio {r: .3e}  damping {d:.3e}  "
            "|step| {s:.3e}  accepted {a}  cg {k}",
            i=step, c=cost, r=ratio, d=damping, s=step_norm, a=accepted, k=cg,
        )

    jax.lax.cond(fresh, first, trial_line)


def trial(rule: Rule, path: Path, state: SolverState, stopping: Stopping, *,
          verbose: bool = False, label: str = "least_squares") -> SolverState:
    """One iteration (module docstring). A state that is not yet linearised
    (``state.linearized`` False) only linearises at ``state.params``."""
    fresh = ~state.linearized
    normal = path.normal(state.system)

    def propose() -> tuple[Array, Array]:
        step, its = path.propose(rule, state.strategy_state, state.system, normal)
        return step, jnp.asarray(its, jnp.int32)

    # the first trial of a fresh state only linearises: no linear solve on the placeholder
    delta, its = jax.lax.cond(
        fresh, lambda: (jnp.zeros_like(normal.grad), jnp.zeros((), jnp.int32)), propose
    )
    step_ok = fresh | jnp.all(jnp.isfinite(delta))
    # a stopped problem's trial is discarded, but a vmapped (or unrolled) loop still
    # computes it: cut it here, so that reverse mode through an unrolled batch does not
    # meet a stopped problem's non-finite system (lineax's transpose raised for the batch)
    delta = jnp.where(step_ok & ~fresh & ~state.done, delta, 0.0)
    trial_params = path.retract(state.params, delta)
    system_new, cost_new, finite = path.linearize(trial_params)
    finite = step_ok & finite
    actual = state.cost - cost_new
    pred = -(normal.grad @ delta + 0.5 * delta @ (normal.hess @ delta))
    tiny = jnp.finfo(pred.dtype).tiny
    ratio = jnp.where(
        pred > tiny,
        actual / jnp.where(pred > tiny, pred, 1.0),
        jnp.where(actual > 0, 1.0, -jnp.inf),
    )
    ratio = jnp.where(finite, ratio, -jnp.inf)
    step_norm = jnp.linalg.norm(delta)
    accepted = jnp.where(fresh, finite, rule._accept(finite, actual, ratio))

    system = select(accepted, system_new, state.system)
    # the fresh trial's linearisation at the start gives the initial cost (what init was
    # given may be a placeholder: graph.solve evaluates the residuals only in the loop)
    params = select(accepted & ~fresh, trial_params, state.params)
    cost = jnp.where(accepted | fresh, cost_new, state.cost)
    better = accepted & ~fresh & (cost_new < state.best_cost)
    best_params = select(better, trial_params, state.best_params)
    best_cost = jnp.where(better | fresh, cost_new, state.best_cost)
    initial_cost = jnp.where(fresh, cost_new, state.initial_cost)
    sstate = select(
        fresh, state.strategy_state, rule._strategy_update(state.strategy_state, ratio, step_norm)
    )
    rejects = jnp.where(accepted, 0, state.rejects + 1).astype(jnp.int32)
    bad_run = nonfinite_run(state.bad_run, accepted, finite)
    rejects = rule._on_failure_rejects(rejects, finite, stopping)
    # a rejection that cannot change the damping (Constant, or clamped at its bound)
    # would repeat the same trial: give up now
    stuck = ~accepted & (rule._damping(sstate) == rule._damping(state.strategy_state))
    rejects = jnp.where(stuck, jnp.maximum(rejects, stopping.max_rejects), rejects)
    num_steps = state.num_steps + jnp.where(fresh, 0, 1).astype(jnp.int32)
    plateau = plateau_count(stopping, state.cost, cost, state.plateau).astype(jnp.int32)
    plateau = jnp.where(fresh, 0, plateau)
    grad_inf = jnp.max(jnp.abs(path.normal(system).grad), initial=0.0)
    _, status = check(
        stopping,
        Trial(
            step=num_steps,
            last=state.cost,
            cost=cost,
            accepted=accepted,
            finite=finite,
            step_norm=step_norm,
            predicted=pred,
            initial=state.initial_cost,
            grad_inf=grad_inf,
            rejects=rejects,
            plateau_count=plateau,
            nonfinite_run=~accepted & bad_run,
            trial_cost=cost_new,
            best=best_cost,
        ),
    )
    status = jnp.where(fresh, start_status(finite, grad_inf, stopping), status)
    hist = state.history
    if hist.shape[0] > 0:
        hist = hist.at[jnp.minimum(num_steps, hist.shape[0] - 1)].set(cost)
    its = jnp.where(fresh, 0, its).astype(jnp.int32)
    if verbose:
        _print(label, fresh, num_steps, cost, ratio, rule._damping(state.strategy_state),
               step_norm, accepted, grad_inf, its)
    return SolverState(
        params=params,
        best_params=best_params,
        cost=cost,
        best_cost=best_cost,
        initial_cost=initial_cost,
        system=system,
        strategy_state=sstate,
        num_steps=num_steps,
        num_accepted=state.num_accepted + (accepted & ~fresh).astype(jnp.int32),
        rejects=jnp.where(fresh, 0, rejects),
        bad_run=jnp.where(fresh, True, bad_run),
        plateau=plateau,
        ratio=ratio,
        step_norm=step_norm,
        accepted=accepted,
        linearized=jnp.asarray(True),
        done=status != Results.RUNNING,
        status=status,
        history=hist,
        linear_iterations=state.linear_iterations + its,
    )


__all__ = ["Path", "Rule", "SolverState", "init", "select", "start_status", "trial"]
