"""Gauss-Newton and Levenberg-Marquardt as equinox Modules with an ``init``/``step`` API.

One ``step`` is one *trial*: propose δ from the linearisation at the current estimate,
evaluate residual and Jacobian at ``X ⊕ δ`` in one pass, then accept (the trial's
linearisation becomes current) or reject (the cached one is kept and only the strategy
state changes). There is no inner retry loop, so under ``vmap`` every problem advances
with its own damping, acceptance and stopping and nothing is shared across the batch.

Example (driving iterations by hand, like PyPose's ``optimizer.step``)::

    solver = LevenbergMarquardt()
    state = solver.init(residual_fn, params, args)
    while not state.done:  # the first step only linearises
        state = solver.step(residual_fn, state, args)
    params = state.best_params
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from ..lie import manifold
from ..results import Results
from .colouring import SparseJacobian, diagonal, identity_like, normal_equations
from .linear import Cholesky, LinearSolver
from .problem import LinearizedResidual, Problem, as_problem
from .stopping import Stopping, Trial, check, nonfinite_run, plateau_count
from .strategies import NormalEquations, Strategy, TrustRegion

Array = jax.Array
PyTree = Any


class SolverState(eqx.Module):
    """Per-problem iteration state (all leaves are arrays; vmap-friendly)."""

    params: PyTree  # current estimate (last accepted)
    best_params: PyTree  # lowest-cost estimate seen
    cost: Array
    best_cost: Array
    initial_cost: Array
    system: NormalEquations  # linearisation at ``params``
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
    history: Array  # (budget + 1,) costs, or (0,) when not recorded


def _print_iteration(fresh: Array, step: Array, cost: Array, ratio: Array, damping: Array,
                     step_norm: Array, accepted: Array, grad_inf: Array) -> None:
    """One verbose line from inside jit: the start (linearisation: cost and ‖g‖∞) or a
    trial step (cost, gain ratio, damping, ‖δ‖, accepted)."""

    def start() -> None:
        jax.debug.print("least_squares start      cost {c:.6e}  |grad|inf {g:.3e}",
                        c=cost, g=grad_inf)

    def trial() -> None:
        jax.debug.print(
            "least_squares iter {i:4d}  cost {c:.6e}  ratio {r: .3e}  damping {d:.3e}  "
            "|step| {s:.3e}  accepted {a}",
            i=step, c=cost, r=ratio, d=damping, s=step_norm, a=accepted,
        )

    jax.lax.cond(fresh, start, trial)


def _select(pred: Array, a: PyTree, b: PyTree) -> PyTree:
    return jax.tree.map(lambda x, y: jnp.where(pred, x, y), a, b)


def _all_finite(*xs: Array) -> Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in xs]))


class AbstractSolver(eqx.Module):
    """Shared machinery; subclasses define how a step is proposed and accepted (and
    declare a ``linear_solver`` field)."""

    # -- subclass hooks ----------------------------------------------------------------
    def _strategy_init(self, dtype: Any) -> Any:
        return jnp.zeros((), dtype)

    def _damping(self, sstate: Any) -> Array:
        return jnp.zeros((), jnp.result_type(sstate))

    @abc.abstractmethod
    def _propose(self, state: SolverState) -> Array:
        """Implemented by subclasses."""

    def _strategy_update(self, sstate: Any, ratio: Array, step_norm: Array) -> Any:
        return sstate

    @abc.abstractmethod
    def _accept(self, finite: Array, actual: Array, ratio: Array) -> Array:
        """Implemented by subclasses."""

    def _on_failure_rejects(self, rejects: Array, finite: Array, stopping: Stopping) -> Array:
        return rejects

    def _diag_bounds(self) -> tuple[float, float]:
        return 0.0, float("inf")

    # -- shared ------------------------------------------------------------------------
    def _system(self, lin: LinearizedResidual) -> NormalEquations:
        hess, grad = normal_equations(lin.jac, lin.res)
        diag = diagonal(hess)
        lo, hi = self._diag_bounds()
        scale = jnp.clip(diag, lo, hi)
        lift = jnp.maximum(scale - diag, 0.0)
        return NormalEquations(lin.jac, lin.res, hess, grad, scale, lift)

    def init(
        self,
        residual_fn: Callable[[PyTree, PyTree], PyTree] | Problem,
        params: PyTree,
        args: PyTree = None,
        *,
        weights: PyTree = None,
        kernel: PyTree = None,
        corrector: Any = None,
        jacobian: str | Callable[..., Array] = "auto",
        stopping: Stopping | None = None,
        history: bool = False,
    ) -> SolverState:
        """Evaluate the cost at ``params`` and build the initial state.

        Raises (via ``eqx.error_if``, also under ``jit``) if ``residual_fn`` is NaN/Inf
        at the initial ``params``. The linearisation is deferred to the first
        :meth:`step` (which only linearises and does not count as an iteration), so a
        compiled loop contains a single copy of the Jacobian computation."""
        problem = as_problem(
            residual_fn, weights=weights, kernel=kernel, corrector=corrector, jacobian=jacobian
        )
        problem.check(params, args)
        stopping = Stopping() if stopping is None else stopping
        out = problem.residual_fn(params, args)
        lin = problem._blocks(out, None)
        bad = ~(jnp.isfinite(lin.cost) & jnp.all(jnp.isfinite(lin.res)))
        cost = eqx.error_if(
            lin.cost,
            bad,
            "least_squares: residual_fn(params, args) returned NaN/Inf at the initial params",
        )
        dtype = cost.dtype
        m, n = lin.res.shape[0], manifold.tangent_size(params)
        mode, pattern = problem.jacobian_mode(params, args)
        if mode == "sparse":  # the coloured path's structures (the loop carry's layout)
            jac0: Any = SparseJacobian(jnp.zeros((m, pattern.num_colours), dtype), pattern)
            hess0: Any = identity_like(jac0.normal())  # dense, BlockHessian or SparseHessian
        else:
            jac0, hess0 = jnp.zeros((m, n), dtype), jnp.eye(n, dtype=dtype)
        system = NormalEquations(
            jac0,
            jnp.zeros((m,), dtype),
            hess0,
            jnp.zeros((n,), dtype),
            jnp.ones((n,), dtype),
            jnp.zeros((n,), dtype),
        )
        hist = jnp.full((stopping.budget + 1,) if history else (0,), jnp.nan, dtype)
        if history:
            hist = hist.at[0].set(cost)
        zero_i = jnp.zeros((), jnp.int32)
        return SolverState(
            params=params,
            best_params=params,
            cost=cost,
            best_cost=cost,
            initial_cost=cost,
            system=system,
            strategy_state=self._strategy_init(dtype),
            num_steps=zero_i,
            num_accepted=zero_i,
            rejects=zero_i,
            bad_run=jnp.asarray(True),
            plateau=zero_i,
            ratio=jnp.zeros((), dtype),
            step_norm=jnp.zeros((), dtype),
            accepted=jnp.asarray(False),
            linearized=jnp.asarray(False),
            done=jnp.asarray(False),
            status=jnp.asarray(Results.RUNNING, jnp.int32),
            history=hist,
        )

    def step(
        self,
        residual_fn: Callable[[PyTree, PyTree], PyTree] | Problem,
        state: SolverState,
        args: PyTree = None,
        *,
        weights: PyTree = None,
        kernel: PyTree = None,
        corrector: Any = None,
        jacobian: str | Callable[..., Array] = "auto",
        stopping: Stopping | None = None,
        verbose: bool = False,
    ) -> SolverState:
        """One trial step (the first call only linearises at the initial params).

        A finished state (``state.done``) is returned unchanged."""
        problem = as_problem(
            residual_fn, weights=weights, kernel=kernel, corrector=corrector, jacobian=jacobian
        )
        stopping = Stopping() if stopping is None else stopping
        new = self._step(problem, state, args, stopping, verbose)
        return _select(state.done, state, new)

    def _step(self, problem: Problem, state: SolverState, args: PyTree, stopping: Stopping,
              verbose: bool) -> SolverState:
        """:meth:`step` without the freeze of finished states (inside ``least_squares``'
        while loop a finished problem is never stepped: the loop, or its vmap batching
        rule, already keeps it)."""
        fresh = ~state.linearized
        sys_ = state.system
        delta = self._propose(state)
        step_ok = fresh | jnp.all(jnp.isfinite(delta))
        delta = jnp.where(step_ok & ~fresh, delta, 0.0)
        _, unravel = manifold.flat_tangent(state.params)
        trial = manifold.retract(state.params, unravel(delta))
        lin = problem.linearize_structured(trial, args)
        finite = step_ok & _all_finite(lin.cost, lin.res, *jax.tree.leaves(lin.jac))
        actual = state.cost - lin.cost
        pred = -(sys_.grad @ delta + 0.5 * delta @ (sys_.hess @ delta))
        tiny = jnp.finfo(pred.dtype).tiny
        ratio = jnp.where(
            pred > tiny,
            actual / jnp.where(pred > tiny, pred, 1.0),
            jnp.where(actual > 0, 1.0, -jnp.inf),
        )
        ratio = jnp.where(finite, ratio, -jnp.inf)
        step_norm = jnp.linalg.norm(delta)
        accepted = jnp.where(fresh, finite, self._accept(finite, actual, ratio))

        new_lin = LinearizedResidual(
            jnp.where(finite, lin.res, 0.0),
            jax.tree.map(lambda j: jnp.where(finite, j, 0.0), lin.jac),
            jnp.where(finite, lin.cost, state.cost),
        )
        system = _select(accepted, self._system(new_lin), sys_)
        params = _select(accepted, trial, state.params)
        cost = jnp.where(accepted, lin.cost, state.cost)
        better = accepted & (lin.cost < state.best_cost)
        best_params = _select(better, trial, state.best_params)
        best_cost = jnp.where(better, lin.cost, state.best_cost)
        sstate = _select(
            fresh,
            state.strategy_state,
            self._strategy_update(state.strategy_state, ratio, step_norm),
        )
        rejects = jnp.where(accepted, 0, state.rejects + 1).astype(jnp.int32)
        bad_run = nonfinite_run(state.bad_run, accepted, finite)
        rejects = self._on_failure_rejects(rejects, finite, stopping)
        # a rejection that cannot change the damping (Constant, or clamped at its bound)
        # would repeat the same trial: give up now
        stuck = ~accepted & (self._damping(sstate) == self._damping(state.strategy_state))
        rejects = jnp.where(stuck, jnp.maximum(rejects, stopping.max_rejects), rejects)
        num_steps = state.num_steps + jnp.where(fresh, 0, 1).astype(jnp.int32)
        plateau = plateau_count(stopping, state.cost, cost, state.plateau).astype(jnp.int32)
        plateau = jnp.where(fresh, 0, plateau)
        grad_inf = jnp.max(jnp.abs(system.grad), initial=0.0)
        done, status = check(
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
            ),
        )
        # the linearisation step: only non-finite Jacobian, gtol or a zero budget stop it
        status0 = jnp.where(
            ~finite,
            Results.NON_FINITE,
            jnp.where(
                grad_inf <= stopping.gtol,
                Results.CONVERGED,
                jnp.where(stopping.budget <= 0, Results.MAX_STEPS, Results.RUNNING),
            ),
        ).astype(jnp.int32)
        status = jnp.where(fresh, status0, status)
        done = status != Results.RUNNING
        hist = state.history
        if hist.shape[0] > 0:
            hist = hist.at[jnp.minimum(num_steps, hist.shape[0] - 1)].set(cost)
        if verbose:
            _print_iteration(fresh, num_steps, cost, ratio, self._damping(state.strategy_state),
                             step_norm, accepted, grad_inf)
        return SolverState(
            params=params,
            best_params=best_params,
            cost=cost,
            best_cost=best_cost,
            initial_cost=state.initial_cost,
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
            done=done,
            status=status,
            history=hist,
        )


class GaussNewton(AbstractSolver):
    """Gauss-Newton: solve ``H δ = −g`` and take every finite step.

    No damping, so a non-finite step or residual (e.g. singular H with
    :class:`~jaxpose.optim.Cholesky`) ends the solve with ``NON_FINITE``; use
    :class:`~jaxpose.optim.SVD` (pseudo-inverse, PyPose GN's default) for rank-deficient
    problems. The best estimate is tracked separately since GN may increase the cost."""

    linear_solver: LinearSolver = Cholesky()

    def _propose(self, state: SolverState) -> Array:
        s = state.system
        return self.linear_solver.solve(s.jac, s.res, s.hess, s.grad, jnp.zeros_like(s.grad))

    def _accept(self, finite: Array, actual: Array, ratio: Array) -> Array:
        return finite

    def _on_failure_rejects(self, rejects: Array, finite: Array, stopping: Stopping) -> Array:
        # GN cannot adapt: a failed trial would repeat identically.
        return jnp.where(finite, rejects, stopping.max_rejects).astype(jnp.int32)


class LevenbergMarquardt(AbstractSolver):
    """Levenberg-Marquardt with a pluggable damping / trust-region ``strategy``.

    Trial system: ``(H + diag(c) + λ·diag(D)) δ = −g`` with D = clamp(diag H, diag_min,
    diag_max) and c lifting diagonal entries below ``diag_min`` (PyPose's ``min``/``max``).
    A trial is accepted when it is finite, lowers the cost and its gain ratio exceeds
    ``accept_ratio`` (0: any decrease, as PyPose). ``strategy`` is one of
    :class:`Constant`, :class:`Adaptive`, :class:`TrustRegion` (default) or
    :class:`Dogleg`."""

    strategy: Strategy = TrustRegion()
    linear_solver: LinearSolver = Cholesky()
    diag_min: float = 1e-6
    diag_max: float = 1e32
    accept_ratio: float = 0.0

    def __check_init__(self) -> None:
        if not isinstance(self.strategy, Strategy):
            raise TypeError(f"strategy: expected a Strategy, got {type(self.strategy).__name__}")
        if not isinstance(self.linear_solver, LinearSolver):
            raise TypeError(
                f"linear_solver: expected a jaxpose.optim LinearSolver, got "
                f"{type(self.linear_solver).__name__}"
            )

    def _diag_bounds(self) -> tuple[float, float]:
        return self.diag_min, self.diag_max

    def _strategy_init(self, dtype: Any) -> Any:
        return self.strategy.init(dtype)

    def _damping(self, sstate: Any) -> Array:
        return self.strategy.damping(sstate)

    def _propose(self, state: SolverState) -> Array:
        return self.strategy.step(state.strategy_state, state.system, self.linear_solver)

    def _strategy_update(self, sstate: Any, ratio: Array, step_norm: Array) -> Any:
        return self.strategy.update(sstate, ratio, step_norm)

    def _accept(self, finite: Array, actual: Array, ratio: Array) -> Array:
        return finite & (actual > 0) & (ratio > self.accept_ratio)


GN = GaussNewton
LM = LevenbergMarquardt

__all__ = ["AbstractSolver", "GaussNewton", "LevenbergMarquardt", "GN", "LM", "SolverState"]
