"""Levenberg–Marquardt damping schedules of GTSAM and Ceres as :mod:`jaxpose.optim` strategies.

Both follow the :class:`jaxpose.optim.Strategy` protocol (``init``/``damping``/``update``
from the gain ratio ρ of each trial; a trial with ρ ≤ 0 or a non-finite one, ρ = −∞, was
rejected), so they also work with :func:`jaxpose.optim.least_squares`, and the sparse
solver :func:`jaxpose.graph.solve` accepts any of the optim strategies as well.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from .._checks import require
from ..optim.strategies import Strategy

Array = jax.Array


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


__all__ = ["LambdaFactor", "Nielsen", "NielsenState"]
