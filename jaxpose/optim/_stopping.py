"""Termination: tolerances and PyPose's StopOnPlateau rule.

All tests are evaluated per problem from scalar state, so under ``vmap`` every problem
stops on its own. One *iteration* is one trial step (accepted or rejected).
"""

from __future__ import annotations

import numbers
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import count_field
from ..results import Results

Array = jax.Array


def check_tolerance(value: object, name: str, *, positive: bool = False) -> None:
    """Refuse a Python or NumPy number that is NaN or negative (``positive``: also zero),
    which would silently switch a test off or on; arrays (possibly traced) pass."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return
    if not (value > 0 if positive else value >= 0):
        kind = "positive" if positive else "non-negative"
        raise ValueError(f"{name}={value!r}: expected a {kind} tolerance")


class StopOnPlateau(eqx.Module):
    """PyPose's ``StopOnPlateau`` semantics per iteration.

    * stop after ``steps`` iterations (caps ``max_steps``);
    * count consecutive iterations whose cost decrease ``last − cost`` is below
      ``decreasing`` (a rejected trial decreases by 0); stop (CONVERGED) once the count
      reaches ``patience``.

    As in PyPose's code (its docstring says "relative"), ``decreasing`` is an absolute
    decrease by default; ``relative=True`` compares ``(last − cost) / last`` instead.
    Units: this library's cost ``0.5·Σρ`` (PyPose's loss is ``Σρ``, twice as large).
    Unlike PyPose, a rejected trial does not stop the solve by itself: it only counts
    towards the patience (PyPose retries inside one step and stops on any rejection).
    """

    steps: int = count_field("StopOnPlateau(steps)")
    patience: int = count_field("StopOnPlateau(patience)", default=5)
    decreasing: float = 1e-3
    relative: bool = eqx.field(default=False, static=True)

    def __check_init__(self) -> None:
        check_tolerance(self.decreasing, "StopOnPlateau(decreasing)")


class Stopping(eqx.Module):
    """Tolerances (all per problem, cost in units of ``0.5·Σρ``).

    * ``max_steps``: iteration budget (→ MAX_STEPS);
    * ``cost_atol``/``cost_rtol``: an accepted step with decrease
      ``0 ≤ last − cost ≤ cost_atol + cost_rtol·last`` → CONVERGED (an accepted increase,
      possible with Gauss-Newton, is not);
    * ``gtol``: ``‖g‖_∞ ≤ gtol`` at the current estimate (g = tangent gradient) →
      CONVERGED;
    * ``xtol``: a finite trial step with ``‖δ‖₂ ≤ xtol`` (no meaningful step left) →
      CONVERGED;
    * always: a rejected finite trial whose *predicted* decrease is positive and below the
      cost's floating-point resolution (16·eps·cost) → CONVERGED (no measurable decrease is
      left); and the third consecutive rejected finite trial (or ``max_rejects``-th, if
      fewer) once the cost is at rounding level, cost ≤ eps²·initial cost (the residual
      has shrunk by the dtype's precision, as in zero-residual problems: further
      "decreases" are rounding noise) → CONVERGED; and a
      rejected finite trial whose cost equals the current one exactly (the step is below
      the variables' floating-point resolution, or the cost is flat along it: a larger
      damping cannot do better) → CONVERGED;
    * ``max_rejects``: that many consecutive rejected trials → DIVERGED (or NON_FINITE
      if the last one was not finite). When ``max_steps`` runs out first while every trial
      since the last accepted one was not finite, the status is NON_FINITE too (not
      MAX_STEPS: with a budget below ``max_rejects`` all-NaN trials would otherwise look
      like a solve that merely needed more steps). A rejected trial that leaves the
      damping unchanged (Constant strategy, damping clamped at its bound, Gauss-Newton)
      ends the solve at once, since the same trial would repeat;
    * ``plateau``: optional :class:`StopOnPlateau`.
    """

    max_steps: int = count_field("Stopping(max_steps)", minimum=0, default=100)
    cost_atol: float = 0.0
    cost_rtol: float = 1e-10
    gtol: float = 1e-10
    xtol: float = 1e-10
    max_rejects: int = count_field("Stopping(max_rejects)", default=64)
    plateau: StopOnPlateau | None = None

    def __check_init__(self) -> None:
        for name in ("cost_atol", "cost_rtol", "gtol", "xtol"):
            check_tolerance(getattr(self, name), name)
        if self.plateau is not None and not isinstance(self.plateau, StopOnPlateau):
            raise TypeError(f"stop: expected StopOnPlateau or None, got {type(self.plateau)}")

    @property
    def budget(self) -> int:
        """Effective iteration budget (``max_steps`` capped by ``plateau.steps``)."""
        if self.plateau is None:
            return self.max_steps
        return min(self.max_steps, self.plateau.steps)


class Trial(NamedTuple):
    """What one iteration measured (inputs to :func:`check`)."""

    step: Array  # iteration count after this trial (int32)
    last: Array  # cost before the trial
    cost: Array  # cost after the trial (== last if rejected)
    trial_cost: Array  # the trial's own cost (accepted or not)
    accepted: Array  # bool
    finite: Array  # bool: trial step, residual and Jacobian all finite
    step_norm: Array  # ‖δ‖₂
    predicted: Array  # decrease predicted by the quadratic model for this trial
    initial: Array  # cost at the start
    grad_inf: Array  # ‖g‖_∞ at the (possibly new) current estimate
    rejects: Array  # consecutive rejected trials so far (int32)
    plateau_count: Array  # consecutive non-decreasing iterations so far (int32)
    nonfinite_run: Array | bool = False  # bool: every trial since the last accepted one
    # (at least this one) was not finite
    best: Array | None = None  # lowest cost seen, this trial included (None: ``cost``)


def nonfinite_run(previous: Array, accepted: Array, finite: Array) -> Array:
    """Update the flag "every trial since the last accepted one was not finite" (start it
    at True; an accepted trial resets it, a finite rejected one clears it)."""
    return jnp.where(accepted, True, previous & ~finite)


def plateau_count(stopping: Stopping, last: Array, cost: Array, count: Array) -> Array:
    """Update the StopOnPlateau counter after one iteration."""
    if stopping.plateau is None:
        return count
    dec = last - cost
    if stopping.plateau.relative:
        dec = dec / jnp.maximum(jnp.abs(last), jnp.finfo(last.dtype).tiny)
    return jnp.where(dec < stopping.plateau.decreasing, count + 1, 0)


_ROUNDING_REJECTS = 3
"""Consecutive rejected trials after which a cost at rounding level (≤ ε²·initial) counts
as converged (:func:`check`)."""


def check(stopping: Stopping, t: Trial) -> tuple[Array, Array]:
    """(done, status) after one iteration; precedence NON_FINITE > CONVERGED > DIVERGED
    > MAX_STEPS."""
    decrease = t.last - t.cost
    # a cost increase (Gauss-Newton takes every finite step) is not convergence
    conv = t.accepted & (decrease >= 0)
    conv = conv & (decrease <= stopping.cost_atol + stopping.cost_rtol * t.last)
    conv = conv | (t.grad_inf <= stopping.gtol)
    conv = conv | (t.finite & (t.step_norm <= stopping.xtol))
    eps = jnp.finfo(t.last.dtype).eps
    # a predicted decrease that is not positive is the model's rounding (or an indefinite
    # H), not a step too small to measure: the damping grows instead
    small = (t.predicted > 0) & (t.predicted <= 16 * eps * jnp.abs(t.last))
    # the cost at the dtype's precision of where it started (zero-residual problems), once
    # trials keep failing: a first rejection there can be an ordinary one after a stiff
    # part was solved exactly (cost 5e33 → 12 in one step; the rule stopped at ‖g‖ = 108)
    rounding = (t.last <= eps * eps * t.initial) & (
        t.rejects >= min(_ROUNDING_REJECTS, stopping.max_rejects))
    noise = small | rounding
    conv = conv | (t.finite & ~t.accepted & noise)
    # a step that changes the cost not even by its last bit
    conv = conv | (t.finite & ~t.accepted & (t.trial_cost == t.last))
    if stopping.plateau is not None:
        conv = conv | (t.plateau_count >= stopping.plateau.patience)
    # a rule that takes uphill steps (Gauss–Newton) can converge above the best point it
    # has seen, which is what the solution returns: that point is not stationary. A rise
    # within the cost tolerance or √ε of the cost is the same optimum (residuals that
    # cancel large values, data on an offset, carry far more rounding than ε·cost)
    best = t.cost if t.best is None else t.best
    rel = jnp.maximum(stopping.cost_rtol, jnp.sqrt(eps))
    above_best = conv & (t.cost - best > stopping.cost_atol + rel * t.cost)
    conv = conv & ~above_best
    stalled = t.rejects >= stopping.max_rejects
    out_of_steps = t.step >= stopping.budget
    nonfinite = (stalled & ~t.finite) | (out_of_steps & ~t.finite & t.nonfinite_run)
    diverged = (stalled & t.finite) | above_best
    status = jnp.where(
        nonfinite,
        Results.NON_FINITE,
        jnp.where(
            conv,
            Results.CONVERGED,
            jnp.where(
                diverged,
                Results.DIVERGED,
                jnp.where(out_of_steps, Results.MAX_STEPS, Results.RUNNING),
            ),
        ),
    )
    status = status.astype(jnp.int32)
    return status != Results.RUNNING, status


__all__ = [
    "StopOnPlateau",
    "Stopping",
    "Trial",
    "check",
    "nonfinite_run",
    "plateau_count",
]
