"""Small benchmark models used by the examples and tests (continuous-time, RK4).

* :class:`CartPole` — state ``[x, ẋ, θ, θ̇]`` (θ = 0 upright), input ``[force]``.
* :class:`Pendulum` — state ``[θ, ω]`` (θ = 0 hanging down), input ``[torque]``.
* :class:`Bicycle` — kinematic bicycle, state ``[px, py, ψ, v]``, input ``[a, δ]``
  (acceleration, steering angle); observes ranges to fixed landmarks and the speed.

Each model checks the sizes of ``x`` and ``u`` (one element, last dimension), raising a
``ValueError`` naming the argument instead of ignoring extra components.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import count_field
from .._safe import safe_norm
from ._checks import check_last
from ._integrators import ContinuousSystem

Array = jax.Array


def _check_sizes(model: Any, x: Array, u: Array, state: str, inputs: str) -> None:
    """``x`` and ``u`` have the model's sizes (the names of their components given)."""
    name = type(model).__name__
    check_last(jnp.asarray(x), len(state.split(", ")), "x", f"{name} state [{state}]")
    check_last(jnp.asarray(u), len(inputs.split(", ")), "u", f"{name} inputs [{inputs}]")


def _check_positive(model: Any, *names: str) -> None:
    """Refuse a known (Python or NumPy) parameter that is not positive and finite: a
    length of 0 divided by zero at the first step (NaN when traced). Traced and JAX-array
    parameters (learned ones) pass."""
    for name in names:
        value = getattr(model, name)
        if isinstance(value, (int, float, np.number)) and not 0 < value < np.inf:
            raise ValueError(f"{type(model).__name__}({name}={value!r}): expected a positive "
                             f"finite value")


class CartPole(ContinuousSystem):
    """Cart-pole (Barto et al. 1983 equations, as PyPose's example); θ = 0 is upright.

    Parameters are array fields (differentiable): ``cart_mass``, ``pole_mass``,
    ``length`` (half pole length), ``gravity``."""

    dt: Any = 0.05
    cart_mass: Any = 1.0
    pole_mass: Any = 0.1
    length: Any = 0.5
    gravity: Any = 9.81
    method: str = eqx.field(static=True, default="rk4")
    substeps: int = count_field("substeps", default=1)

    def __check_init__(self) -> None:
        _check_positive(self, "cart_mass", "length")  # a massless pole is a valid limit

    def derivative(self, x: Array, u: Array, tau: Any) -> Array:
        _check_sizes(self, x, u, "x, ẋ, θ, θ̇", "force")
        _, xd, th, thd = x[0], x[1], x[2], x[3]
        force = u[0]
        total = self.cart_mass + self.pole_mass
        pml = self.pole_mass * self.length
        s, c = jnp.sin(th), jnp.cos(th)
        temp = (force + pml * thd**2 * s) / total
        thdd = (self.gravity * s - c * temp) / (
            self.length * (4.0 / 3.0 - self.pole_mass * c**2 / total)
        )
        xdd = temp - pml * thdd * c / total
        return jnp.stack([xd, xdd, thd, thdd])


class Pendulum(ContinuousSystem):
    """Damped pendulum ``θ̈ = −(g/l) sin θ − b θ̇ + u / (m l²)``; θ = 0 hangs down."""

    dt: Any = 0.05
    length: Any = 1.0
    mass: Any = 1.0
    damping: Any = 0.1
    gravity: Any = 9.81
    method: str = eqx.field(static=True, default="rk4")
    substeps: int = count_field("substeps", default=1)

    def __check_init__(self) -> None:
        _check_positive(self, "length", "mass")

    def derivative(self, x: Array, u: Array, tau: Any) -> Array:
        _check_sizes(self, x, u, "θ, ω", "torque")
        th, om = x[0], x[1]
        acc = (
            -(self.gravity / self.length) * jnp.sin(th)
            - self.damping * om
            + u[0] / (self.mass * self.length**2)
        )
        return jnp.stack([om, acc])


class Bicycle(ContinuousSystem):
    """Kinematic bicycle: ``ṗx = v cos ψ``, ``ṗy = v sin ψ``, ``ψ̇ = v tan δ / L``,
    ``v̇ = a``. Observation: distances to ``landmarks`` (k, 2) followed by the speed,
    shape (k + 1,). A distance is a safe norm: exact everywhere, and at a landmark
    (distance 0, where ‖d‖ has no derivative) its derivative is the subgradient 0 instead
    of NaN, so an EKF linearising there stays finite."""

    dt: Any = 0.1
    wheelbase: Any = 2.5
    landmarks: Array = eqx.field(
        default_factory=lambda: jnp.array([[0.0, 0.0], [20.0, 0.0], [0.0, 20.0], [20.0, 20.0]])
    )
    method: str = eqx.field(static=True, default="rk4")
    substeps: int = count_field("substeps", default=1)

    def __check_init__(self) -> None:
        _check_positive(self, "wheelbase")

    def derivative(self, x: Array, u: Array, tau: Any) -> Array:
        _check_sizes(self, x, u, "px, py, ψ, v", "a, δ")
        psi, v = x[2], x[3]
        a, delta = u[0], u[1]
        return jnp.stack(
            [v * jnp.cos(psi), v * jnp.sin(psi), v * jnp.tan(delta) / self.wheelbase, a]
        )

    def observation(self, x: Array, u: Array, t: Any = 0) -> Array:
        _check_sizes(self, x, u, "px, py, ψ, v", "a, δ")
        d = x[None, :2] - jnp.asarray(self.landmarks).astype(jnp.result_type(x))  # x's dtype
        return jnp.concatenate([safe_norm(d), x[3:4]])  # finite derivative at a landmark
