"""Discrete-time systems, linearisation, rollouts and integrators.

``System`` (base: ``state_transition(x, u, t)``, ``observation(x, u, t)``), ``LTI``,
``LTV``, ``NLS`` (per-element ``jacfwd`` linearisation), :func:`rollout` (``lax.scan``),
``ContinuousSystem`` / ``Discretized`` with Euler and RK4 steps, and benchmark models.
"""

from ._integrators import (
    ContinuousSystem,
    Discretized,
    euler_step,
    integrate,
    rk4_step,
)
from ._models import Bicycle, CartPole, Pendulum
from ._system import LTI, LTV, NLS, LinearizedSystem, System, rollout

__all__ = [
    "LTI",
    "LTV",
    "NLS",
    "Bicycle",
    "CartPole",
    "ContinuousSystem",
    "Discretized",
    "LinearizedSystem",
    "Pendulum",
    "System",
    "euler_step",
    "integrate",
    "rk4_step",
    "rollout",
]
