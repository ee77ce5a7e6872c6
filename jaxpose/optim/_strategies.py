"""Damping / trust-region strategies for Levenberg-Marquardt.

A strategy owns a small state (a pytree of scalars, one per problem, so every problem of
a ``vmap`` keeps its own) and two rules:

* ``step(state, system, linear_solver)`` → the trial step δ. The LM strategies solve
  ``(H + diag(c) + λ·diag(D)) δ = −g`` where D = clamp(diag H, diag_min, diag_max) is
  Marquardt's scaling and c lifts tiny diagonal entries up to ``diag_min`` (PyPose's
  diagonal clamp). λ is taken from the state afresh for every trial, so damping never
  compounds across rejected trials (PyPose adds λ·diag(A) to the already-damped A).
* ``update(state, ratio, step_norm)`` → new state, from the gain ratio
  ρ = (actual cost decrease) / (decrease predicted by the quadratic model), called after
  every trial, accepted or not. A non-finite trial has ρ = −∞.

PyPose's rules (:class:`Constant`, :class:`Adaptive`, :class:`TrustRegion`), Powell's
:class:`Dogleg`, GTSAM's :class:`LambdaFactor` and Nielsen's rule as in Ceres
(:class:`Nielsen`); every one works with :func:`~jaxpose.optim.least_squares` and
:func:`jaxpose.graph.solve`.
"""

from __future__ import annotations

import abc
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import require
from .._safe import safe_norm, safe_sqrt
from ._linear import LinearSolver

Array = jax.Array


class NormalEquations(NamedTuple):
    """Gauss-Newton normal equations at the current estimate, handed to
    :meth:`Strategy.step` (all whitened/corrected; the strategy adds the damping).

    jac (m, n), res (m,), hess = jacᵀjac (n, n), grad = jacᵀres (n,),
    scale = clamp(diag hess, diag_min, diag_max) (n,), lift = scale − diag hess ≥ 0 on
    entries that were clamped up (n,)."""

    jac: Array
    res: Array
    hess: Array
    grad: Array
    scale: Array
    lift: Array


def _check_ratio_rule(name: str, high: float, low: float, up: float, down: float,
                      min: float, max: float) -> None:
    """The gain-ratio thresholds and factors shared by :class:`Adaptive` and
    :class:`TrustRegion`; errors name ``name(field)``."""
    require(f"{name}(high)", high > 0, f"has to be positive, got {high!r}")
    require(f"{name}(low)", low > 0, f"has to be positive, got {low!r}")
    require(f"{name}(up)", up > 1, f"has to be larger than 1, got {up!r}")
    require(f"{name}(down)", 0 < down < 1, f"has to be in (0, 1), got {down!r}")
    require(f"{name}(min, max)", 0 < min <= max, f"need 0 < min <= max, got {min}, {max}")


class Strategy(eqx.Module):
    """Base class: Levenberg-Marquardt damping with a state-dependent λ."""

    @abc.abstractmethod
    def init(self, dtype: Any) -> Any:
        """Initial strategy state (a pytree of scalars of ``dtype``, one per problem)."""

    @abc.abstractmethod
    def damping(self, state: Any) -> Array:
        """Current damping λ (for trust-region strategies, 1/radius)."""

    @abc.abstractmethod
    def update(self, state: Any, ratio: Array, step_norm: Array) -> Any:
        """New state from the gain ratio ρ (scalar, −∞ for a non-finite trial) and ‖δ‖.

        Called after every trial, accepted or rejected.
        """

    def step(self, state: Any, system: NormalEquations, linear_solver: LinearSolver) -> Array:
        """Trial step δ (n,): solves (H + diag(c) + λ·diag(D)) δ = −g with ``linear_solver``.

        λ comes from ``state`` afresh for every trial (damping never compounds).
        """
        lam = self.damping(state)
        diag_add = system.lift + lam * system.scale
        return linear_solver.solve(system.jac, system.res, system.hess, system.grad, diag_add)


class Constant(Strategy):
    """λ stays at ``damping`` (PyPose ``Constant``)."""

    damping_value: float = 1e-6

    def __init__(self, damping: float = 1e-6):
        require("Constant(damping)", damping > 0, f"has to be positive, got {damping!r}")
        self.damping_value = damping

    def init(self, dtype: Any) -> Array:
        return jnp.asarray(self.damping_value, dtype)

    def damping(self, state: Array) -> Array:
        return state

    def update(self, state: Array, ratio: Array, step_norm: Array) -> Array:
        return state


class Adaptive(Strategy):
    """PyPose ``Adaptive``: ρ > high → λ·down; low < ρ ≤ high → λ; else λ·up;
    then λ ← clamp(λ, min, max)."""

    damping_value: float = 1e-6
    high: float = 0.5
    low: float = 1e-3
    up: float = 2.0
    down: float = 0.5
    min: float = 1e-6
    max: float = 1e16

    def __init__(
        self,
        damping: float = 1e-6,
        high: float = 0.5,
        low: float = 1e-3,
        up: float = 2.0,
        down: float = 0.5,
        min: float = 1e-6,
        max: float = 1e16,
    ):
        require("Adaptive(damping)", damping > 0, f"has to be positive, got {damping!r}")
        _check_ratio_rule("Adaptive", high, low, up, down, min, max)
        self.damping_value, self.high, self.low = damping, high, low
        self.up, self.down, self.min, self.max = up, down, min, max

    def init(self, dtype: Any) -> Array:
        return jnp.asarray(self.damping_value, dtype)

    def damping(self, state: Array) -> Array:
        return state

    def update(self, state: Array, ratio: Array, step_norm: Array) -> Array:
        lam = jnp.where(
            ratio > self.high,
            state * self.down,
            jnp.where(ratio > self.low, state, state * self.up),
        )
        return jnp.clip(lam, self.min, self.max)


class TrustRegionState(NamedTuple):
    """State of :class:`TrustRegion`: damping λ = 1/Δ and the current shrink factor (scalars)."""
    damping: Array  # λ = 1 / radius
    down: Array  # current shrink factor


class TrustRegion(Strategy):
    """PyPose ``TrustRegion`` (LM's default): radius Δ = 1/λ.

    ρ > high → Δ·up and down ← down₀; low < ρ ≤ high → Δ and down ← down₀;
    else Δ·down and down ← down·factor (shrinking faster after repeated failures);
    then down and Δ are clamped to [min, max] and λ = 1/Δ."""

    radius: float = 1e6
    high: float = 0.5
    low: float = 1e-3
    up: float = 2.0
    down: float = 0.5
    factor: float = 0.5
    min: float = 1e-6
    max: float = 1e16

    def __init__(
        self,
        radius: float = 1e6,
        high: float = 0.5,
        low: float = 1e-3,
        up: float = 2.0,
        down: float = 0.5,
        factor: float = 0.5,
        min: float = 1e-6,
        max: float = 1e16,
    ):
        require("TrustRegion(radius)", radius > 0, f"has to be positive, got {radius!r}")
        require("TrustRegion(factor)", 0 < factor < 1, f"has to be in (0, 1), got {factor!r}")
        _check_ratio_rule("TrustRegion", high, low, up, down, min, max)
        self.radius, self.high, self.low, self.up = radius, high, low, up
        self.down, self.factor, self.min, self.max = down, factor, min, max

    def init(self, dtype: Any) -> TrustRegionState:
        return TrustRegionState(
            jnp.asarray(1.0 / self.radius, dtype), jnp.asarray(self.down, dtype)
        )

    def damping(self, state: TrustRegionState) -> Array:
        return state.damping

    def update(self, state: TrustRegionState, ratio: Array, step_norm: Array) -> TrustRegionState:
        radius = 1.0 / state.damping
        very, ok = ratio > self.high, ratio > self.low
        radius = jnp.where(very, radius * self.up, jnp.where(ok, radius, radius * state.down))
        down = jnp.where(ok, jnp.asarray(self.down, radius.dtype), state.down * self.factor)
        down = jnp.clip(down, self.min, self.max)
        radius = jnp.clip(radius, self.min, self.max)
        return TrustRegionState(1.0 / radius, down)


class Dogleg(Strategy):
    """Powell's dogleg trust region (Nocedal & Wright, Alg. 4.1 / §4.1).

    Step: the Gauss-Newton step δ_gn = −H⁻¹g if ‖δ_gn‖ ≤ Δ; else the Cauchy point
    δ_sd = −(gᵀg / gᵀHg) g clipped to the boundary if ‖δ_sd‖ ≥ Δ; else the point of the
    segment δ_sd → δ_gn on the boundary ‖δ‖ = Δ. (If δ_gn is not finite, e.g. singular H,
    the clipped Cauchy step is used.)
    Radius: ρ < low → Δ·down; ρ > high and the step reached the boundary → Δ·up; then
    Δ ← clamp(Δ, min, max). ``damping`` reports 1/Δ."""

    radius: float = 1.0
    high: float = 0.75
    low: float = 0.25
    up: float = 2.0
    down: float = 0.25
    min: float = 1e-12
    max: float = 1e12

    def __init__(
        self,
        radius: float = 1.0,
        high: float = 0.75,
        low: float = 0.25,
        up: float = 2.0,
        down: float = 0.25,
        min: float = 1e-12,
        max: float = 1e12,
    ):
        require("Dogleg(radius)", radius > 0, f"has to be positive, got {radius!r}")
        require("Dogleg(low, high)", 0 <= low < high, f"need 0 <= low < high, got {low}, {high}")
        require("Dogleg(up)", up > 1, f"has to be larger than 1, got {up!r}")
        require("Dogleg(down)", 0 < down < 1, f"has to be in (0, 1), got {down!r}")
        require("Dogleg(min, max)", 0 < min <= max, f"need 0 < min <= max, got {min}, {max}")
        self.radius, self.high, self.low, self.up = radius, high, low, up
        self.down, self.min, self.max = down, min, max

    def init(self, dtype: Any) -> Array:
        return jnp.asarray(self.radius, dtype)

    def damping(self, state: Array) -> Array:
        return 1.0 / state

    def update(self, state: Array, ratio: Array, step_norm: Array) -> Array:
        at_boundary = step_norm >= 0.99 * state
        radius = jnp.where(
            ratio < self.low,
            state * self.down,
            jnp.where((ratio > self.high) & at_boundary, state * self.up, state),
        )
        return jnp.clip(radius, self.min, self.max)

    def step(self, state: Array, system: NormalEquations, linear_solver: LinearSolver) -> Array:
        radius = state
        g, h = system.grad, system.hess
        gn = linear_solver.solve(system.jac, system.res, h, g, system.lift)
        gn_ok = jnp.all(jnp.isfinite(gn))
        gn = jnp.where(gn_ok, gn, 0.0)
        # safe norms and root: the step is differentiated (adjoint="unrolled") also at
        # g = 0 (a finished lane that vmap keeps stepping)
        gn_norm = safe_norm(gn)
        # Cauchy point along the unit direction u = g/‖g‖: ‖g‖²/gᵀHg = ‖g‖/uᵀHu, whose
        # two factors do not overflow for large residuals (gᵀg did: inf/inf, a NaN step);
        # ‖g‖ = m·‖g/m‖ with m = max |gᵢ|
        m = jnp.max(jnp.abs(g), initial=0.0)
        gs = g / jnp.where(m > 0, m, 1.0)
        gs_norm = safe_norm(gs)
        u = gs / jnp.where(gs_norm > 0, gs_norm, 1.0)
        g_norm = m * gs_norm
        uhu = u @ (h @ u)
        curved = uhu > 0
        sd_norm = jnp.where(curved, g_norm / jnp.where(curved, uhu, 1.0), 0.0)
        sd = -sd_norm * u
        boundary_sd = -radius * u
        # segment sd → gn intersecting ‖δ‖ = Δ: ‖sd + τ d‖² = Δ², τ ∈ [0, 1]
        d = gn - sd
        a = d @ d
        b = 2.0 * (sd @ d)
        c = sd_norm**2 - radius**2
        disc = safe_sqrt(b * b - 4.0 * a * c)
        denom = b + disc
        tau = jnp.where(denom > 0, -2.0 * c / jnp.where(denom > 0, denom, 1.0), 0.0)
        tau = jnp.clip(tau, 0.0, 1.0)
        blend = sd + tau * d
        use_gn = gn_ok & (gn_norm <= radius)
        use_sd = (~gn_ok) | (~curved) | (sd_norm >= radius)
        return jnp.where(use_gn, gn, jnp.where(use_sd, boundary_sd, blend))


class LambdaFactor(Strategy):
    """GTSAM's rule: λ ← max(λ/factor, min) after an accepted trial, λ ← max(λ, min)·factor
    after a rejected one, clamped to ``max`` (a rejection at ``max`` ends the solve)."""

    damping_value: float = 1e-5
    factor: float = 10.0
    min: float = 1e-15
    max: float = 1e16

    def __init__(self, damping: float = 1e-5, factor: float = 10.0, min: float = 1e-15,
                 max: float = 1e16):
        require("LambdaFactor(damping)", damping > 0, f"has to be positive, got {damping!r}")
        require("LambdaFactor(factor)", factor > 1, f"has to be larger than 1, got {factor!r}")
        require("LambdaFactor(min, max)", 0 < min <= max, f"need 0 < min <= max, got {min}, {max}")
        self.damping_value, self.factor, self.min, self.max = damping, factor, min, max

    def init(self, dtype: Any) -> Array:
        return jnp.asarray(self.damping_value, dtype)

    def damping(self, state: Array) -> Array:
        return state

    def update(self, state: Array, ratio: Array, step_norm: Array) -> Array:
        lam = jnp.where(ratio > 0, jnp.maximum(state / self.factor, self.min),
                        jnp.maximum(state, self.min) * self.factor)
        return jnp.minimum(lam, self.max)


class NielsenState(NamedTuple):
    """State of :class:`Nielsen`: damping λ and its growth factor ν (scalars)."""

    damping: Array
    nu: Array


class Nielsen(Strategy):
    """Nielsen's rule (Ceres' LM): accepted → λ·max(1/3, 1 − (2ρ − 1)³) and ν = 2;
    rejected → λ·ν and ν ← 2ν; λ clamped to [min, max]."""

    damping_value: float = 1e-4
    min: float = 1e-15
    max: float = 1e16

    def __init__(self, damping: float = 1e-4, min: float = 1e-15, max: float = 1e16):
        require("Nielsen(damping)", damping > 0, f"has to be positive, got {damping!r}")
        require("Nielsen(min, max)", 0 < min <= max, f"need 0 < min <= max, got {min}, {max}")
        self.damping_value, self.min, self.max = damping, min, max

    def init(self, dtype: Any) -> NielsenState:
        return NielsenState(jnp.asarray(self.damping_value, dtype), jnp.asarray(2.0, dtype))

    def damping(self, state: NielsenState) -> Array:
        return state.damping

    def update(self, state: NielsenState, ratio: Array, step_norm: Array) -> NielsenState:
        ok = ratio > 0
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * jnp.where(ok, ratio, 0.0) - 1.0) ** 3)
        lam = jnp.where(ok, state.damping * shrink, jnp.maximum(state.damping, self.min) * state.nu)
        nu = jnp.where(ok, 2.0, 2.0 * state.nu)
        return NielsenState(jnp.clip(lam, self.min, self.max), nu.astype(state.nu.dtype))


__all__ = [
    "NormalEquations",
    "Strategy",
    "Constant",
    "Adaptive",
    "TrustRegion",
    "TrustRegionState",
    "Dogleg",
    "LambdaFactor",
    "Nielsen",
    "NielsenState",
]
