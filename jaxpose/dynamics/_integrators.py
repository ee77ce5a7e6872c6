"""Fixed-step integrators that turn continuous dynamics ``ẋ = f(x, u, τ)`` into a
discrete :class:`~jaxpose.dynamics.System`.

The control ``u`` is held constant over a step (zero-order hold). Discrete step ``t``
starts at continuous time ``τ = t · dt``.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count, count_field
from ._system import System

Array = jax.Array
Deriv = Callable[[Array, Array, Any], Array]

METHODS = ("euler", "rk4")


def euler_step(f: Deriv, x: Array, u: Array, tau: Any, dt: Any) -> Array:
    """One explicit Euler step: ``x + dt · f(x, u, τ)``."""
    return x + dt * f(x, u, tau)


def rk4_step(f: Deriv, x: Array, u: Array, tau: Any, dt: Any) -> Array:
    """One classical fourth-order Runge–Kutta step with ``u`` held constant."""
    k1 = f(x, u, tau)
    k2 = f(x + 0.5 * dt * k1, u, tau + 0.5 * dt)
    k3 = f(x + 0.5 * dt * k2, u, tau + 0.5 * dt)
    k4 = f(x + dt * k3, u, tau + dt)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


_STEPPERS = {"euler": euler_step, "rk4": rk4_step}


def integrate(
    f: Deriv, x: Array, u: Array, tau: Any, dt: Any, method: str = "rk4", substeps: int = 1
) -> Array:
    """Advance ``x`` by ``dt`` with ``substeps`` steps of ``method`` (``"euler"``/``"rk4"``)."""
    substeps = _check_integration(method, substeps)
    step = _STEPPERS[method]
    h = dt / substeps
    for i in range(substeps):
        x = step(f, x, u, tau + i * h, h)
    return x


def _check_integration(method: Any, substeps: Any, dt: Any = None) -> int:
    """``substeps`` as an int, refusing an unknown ``method``, ``substeps`` < 1 and a
    known ``dt`` ≤ 0 or NaN (traced ``dt`` pass)."""
    if method not in _STEPPERS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if isinstance(dt, (int, float, np.number)) and not dt > 0:
        raise ValueError(f"dt: expected a positive time step, got {dt!r}")
    return check_count(substeps, "substeps")


class ContinuousSystem(System):
    """Base for continuous-time models: implement :meth:`derivative` (ẋ for one element);
    ``state_transition`` integrates it over ``dt`` with ``method`` and ``substeps``.

    Subclasses declare ``dt`` (and optionally ``method``/``substeps``) as fields."""

    dt: eqx.AbstractVar[Any]

    @abc.abstractmethod
    def derivative(self, x: Array, u: Array, tau: Any) -> Array:
        """``ẋ = f(x, u, τ)`` at continuous time ``τ``."""

    @property
    def _method(self) -> str:
        return getattr(self, "method", "rk4")

    @property
    def _substeps(self) -> int:
        return getattr(self, "substeps", 1)

    def __check_init__(self) -> None:  # at construction, not at the first step
        _check_integration(self._method, self._substeps, self.dt)

    def state_transition(self, x: Array, u: Array, t: Any = 0) -> Array:
        tau = jnp.asarray(t) * self.dt
        return integrate(self.derivative, x, u, tau, self.dt, self._method, self._substeps)


class Discretized(System):
    """Wrap a plain function ``f(x, u, τ) → ẋ`` (and optional ``observe(x, u, t)``)
    into a discrete system with step ``dt``. ``f`` may be an equinox Module whose
    arrays are differentiable parameters."""

    f: Deriv
    dt: Any
    method: str = eqx.field(static=True, default="rk4")
    substeps: int = count_field("substeps", default=1)
    observe: Callable[..., Array] | None = None

    def __check_init__(self) -> None:
        _check_integration(self.method, self.substeps, self.dt)

    def state_transition(self, x: Array, u: Array, t: Any = 0) -> Array:
        tau = jnp.asarray(t) * self.dt
        return integrate(self.f, x, u, tau, self.dt, self.method, self.substeps)

    def observation(self, x: Array, u: Array, t: Any = 0) -> Array:
        return x if self.observe is None else self.observe(x, u, t)
