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
from . import _iterate
from ._colouring import SparseJacobian, diagonal, identity_like, normal_equations
from ._iterate import SolverState
from ._linear import Cholesky, LinearSolver
from ._problem import LinearizedResidual, Problem, as_problem
from ._stopping import Stopping
from ._strategies import NormalEquations, Strategy, TrustRegion

Array = jax.Array
PyTree = Any


def _all_finite(*xs: Array) -> Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in xs]))


def _setup(residual_fn: Callable[[PyTree, PyTree], PyTree] | Problem, stopping: Stopping | None,
           **options: Any) -> tuple[Problem, Stopping]:
    """The problem and stopping rule of :meth:`AbstractSolver.init`/``step``."""
    return as_problem(residual_fn, **options), Stopping() if stopping is None else stopping


INITIAL_NOT_FINITE = (
    "least_squares: residual_fn(params, args) returned NaN/Inf at the initial params"
)


class AbstractSolver(eqx.Module):
    """Shared machinery; subclasses define how a step is proposed and accepted (and
    declare a ``linear_solver`` field). They are the damping/acceptance rule of the one
    iteration core (:mod:`jaxpose.optim._iterate`), which ``jaxpose.graph.solve`` uses
    too."""

    # -- subclass hooks ----------------------------------------------------------------
    def _strategy_init(self, dtype: Any) -> Any:
        return jnp.zeros((), dtype)

    def _damping(self, sstate: Any) -> Array:
        return jnp.zeros((), jnp.result_type(sstate))

    @abc.abstractmethod
    def _propose(self, sstate: Any, system: NormalEquations, linear_solver: Any) -> Array:
        """Trial step δ (n,) from the system with ``linear_solver`` (its ``solve``)."""

    def _strategy_update(self, sstate: Any, ratio: Array, step_norm: Array) -> Any:
        return sstate

    @abc.abstractmethod
    def _accept(self, finite: Array, actual: Array, ratio: Array) -> Array:
        """Whether a trial (finite?, actual decrease, gain ratio) is accepted."""

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
        problem, stopping = _setup(residual_fn, stopping, weights=weights, kernel=kernel,
                                   corrector=corrector, jacobian=jacobian)
        return self._init(problem, params, args, stopping, history=history, evaluate=True)

    def _init(self, problem: Problem, params: PyTree, args: PyTree, stopping: Stopping, *,
              history: bool, evaluate: bool) -> SolverState:
        """:meth:`init` of a set-up problem. ``evaluate=False`` (``least_squares``' loop,
        whose first trial linearises at ``params`` and sets the initial cost) takes only
        the residuals' shape: the caller checks the initial cost after the loop."""
        problem.check(params, args)

        def blocks() -> Any:
            return problem._blocks(problem.residual_fn(params, args), None)

        if evaluate:
            lin = blocks()
            bad = ~(jnp.isfinite(lin.cost) & jnp.all(jnp.isfinite(lin.res)))
            cost = eqx.error_if(lin.cost, bad, INITIAL_NOT_FINITE)
        else:
            lin = jax.eval_shape(blocks)
            cost = jnp.full((), jnp.nan, lin.cost.dtype)  # set by the first trial
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
        return _iterate.init(self, params, system, cost, stopping, history=history)

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
        problem, stopping = _setup(residual_fn, stopping, weights=weights, kernel=kernel,
                                   corrector=corrector, jacobian=jacobian)
        new = self._step(problem, state, args, stopping, verbose)
        return _iterate.select(state.done, state, new)

    def _step(self, problem: Problem, state: SolverState, args: PyTree, stopping: Stopping,
              verbose: bool) -> SolverState:
        """:meth:`step` without the freeze of finished states (inside ``least_squares``'
        while loop a finished problem is never stepped: the loop, or its vmap batching
        rule, already keeps it)."""
        path = _DensePath(self, problem, args)
        return _iterate.trial(self, path, state, stopping, verbose=verbose)


class _DensePath(eqx.Module):
    """The dense path of the shared iteration (:mod:`jaxpose.optim._iterate`): the
    problem's (possibly coloured) Jacobian, normal equations carried as
    :class:`NormalEquations`, the solver's own linear solver."""

    solver: AbstractSolver
    problem: Problem
    args: PyTree

    def linearize(self, params: PyTree) -> tuple[NormalEquations, Array, Array]:
        lin = self.problem.linearize_structured(params, self.args)
        finite = _all_finite(lin.cost, lin.res, *jax.tree.leaves(lin.jac))
        safe = LinearizedResidual(
            jnp.where(finite, lin.res, 0.0),
            jax.tree.map(lambda j: jnp.where(finite, j, 0.0), lin.jac),
            lin.cost,
        )
        return self.solver._system(safe), lin.cost, finite

    def normal(self, system: NormalEquations) -> NormalEquations:
        return system

    def propose(self, rule: AbstractSolver, sstate: Any, system: NormalEquations,
                normal: NormalEquations) -> tuple[Array, Array]:
        return rule._propose(sstate, normal, self.solver.linear_solver), jnp.zeros((), jnp.int32)

    def retract(self, params: PyTree, delta: Array) -> PyTree:
        # the estimate keeps its dtype: float64 data promote the residual, the Jacobian
        # and so δ, but float32 params stay float32 (the loop's carry)
        zero, unravel = manifold.flat_tangent(params)
        return manifold.retract(params, unravel(delta.astype(zero.dtype)))


class GaussNewton(AbstractSolver):
    """Gauss-Newton: solve ``H δ = −g`` and take every finite step.

    No damping, so a non-finite step or residual (e.g. singular H with
    :class:`~jaxpose.optim.Cholesky`) ends the solve with ``NON_FINITE``; use
    :class:`~jaxpose.optim.SVD` (pseudo-inverse, PyPose GN's default) for rank-deficient
    problems. GN may increase the cost: the solution is the best estimate seen, and if the
    iterates converge above it the status is ``DIVERGED`` (the best one is not stationary)."""

    linear_solver: LinearSolver = Cholesky()

    def _propose(self, sstate: Any, system: NormalEquations, linear_solver: Any) -> Array:
        s = system
        return linear_solver.solve(s.jac, s.res, s.hess, s.grad, jnp.zeros_like(s.grad))

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
        # outside these a trial is never accepted (DIVERGED at the start) or the damping
        # is not finite; checked where the values are Python numbers
        values = (self.diag_min, self.diag_max, self.accept_ratio)
        if all(isinstance(v, int | float) for v in values) and not (
                0 <= self.diag_min <= self.diag_max and 0 <= self.accept_ratio < 1):
            raise ValueError(f"LevenbergMarquardt: expected 0 ≤ diag_min ≤ diag_max and "
                             f"0 ≤ accept_ratio < 1, got diag_min={self.diag_min!r}, "
                             f"diag_max={self.diag_max!r}, accept_ratio={self.accept_ratio!r}")
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

    def _propose(self, sstate: Any, system: NormalEquations, linear_solver: Any) -> Array:
        return self.strategy.step(sstate, system, linear_solver)

    def _strategy_update(self, sstate: Any, ratio: Array, step_norm: Array) -> Any:
        return self.strategy.update(sstate, ratio, step_norm)

    def _accept(self, finite: Array, actual: Array, ratio: Array) -> Array:
        return finite & (actual > 0) & (ratio > self.accept_ratio)


GN = GaussNewton
LM = LevenbergMarquardt

__all__ = ["AbstractSolver", "GaussNewton", "LevenbergMarquardt", "GN", "LM", "SolverState"]
