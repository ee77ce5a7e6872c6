"""Robust kernels ρ(s) of the squared (whitened) residual norm s = rᵀ W r ≥ 0.

Convention: the solvers minimise ``0.5 · Σ_i ρ(s_i)`` over residual blocks i, so the
trivial kernel ρ(s) = s gives the plain ``0.5 · Σ rᵀ W r``. Every kernel below has
ρ(0) = 0 and, unless stated otherwise, ρ'(0) = 1 (quadratic near the origin), matching
PyPose's / Ceres' definitions. Each kernel provides

* ``__call__(s)`` → ρ(s),
* ``derivative(s)`` → ρ'(s) (used by every corrector),
* ``second_derivative(s)`` → ρ''(s) (used by :class:`~jaxpose.optim.Triggs`),

all elementwise on arrays of any shape, NaN-free at s = 0 under forward and reverse
mode (double-``where`` for square roots and piecewise branches).
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp

Array = jax.Array


def _check_positive(name: str, **values: float) -> None:
    for key, val in values.items():
        if isinstance(val, (int, float)) and not val > 0:
            raise ValueError(f"{name}({key}={val!r}): {key} has to be positive")


def _safe_sqrt(s: Array) -> Array:
    """sqrt(s) with a finite (zero) derivative at s = 0."""
    pos = s > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, s, 1.0)), 0.0)


class Kernel(eqx.Module):
    """Base class: ρ(s) with analytic first and second derivatives."""

    @abc.abstractmethod
    def __call__(self, s: Array) -> Array:
        """ρ(s), elementwise on s = rᵀWr ≥ 0 of any shape."""

    @abc.abstractmethod
    def derivative(self, s: Array) -> Array:
        """ρ'(s), elementwise (the IRLS weight used by every corrector)."""

    @abc.abstractmethod
    def second_derivative(self, s: Array) -> Array:
        """ρ''(s), elementwise (used by :class:`~jaxpose.optim.Triggs`)."""


class Trivial(Kernel):
    """ρ(s) = s (no robustification)."""

    def __call__(self, s: Array) -> Array:
        return s

    def derivative(self, s: Array) -> Array:
        return jnp.ones_like(s)

    def second_derivative(self, s: Array) -> Array:
        return jnp.zeros_like(s)


class Huber(Kernel):
    """ρ(s) = s for s ≤ δ², 2δ√s − δ² otherwise (quadratic core, linear tails)."""

    delta: float = 1.0

    def __check_init__(self) -> None:
        _check_positive("Huber", delta=self.delta)

    def __call__(self, s: Array) -> Array:
        d = self.delta
        inner = s <= d * d
        return jnp.where(inner, s, 2.0 * d * _safe_sqrt(jnp.where(inner, d * d, s)) - d * d)

    def derivative(self, s: Array) -> Array:
        d = self.delta
        inner = s <= d * d
        return jnp.where(inner, 1.0, d / _safe_sqrt(jnp.where(inner, 1.0, s)))

    def second_derivative(self, s: Array) -> Array:
        d = self.delta
        inner = s <= d * d
        so = jnp.where(inner, 1.0, s)
        return jnp.where(inner, 0.0, -0.5 * d / (so * jnp.sqrt(so)))


class PseudoHuber(Kernel):
    """ρ(s) = 2δ² (√(1 + s/δ²) − 1), a smooth Huber."""

    delta: float = 1.0

    def __check_init__(self) -> None:
        _check_positive("PseudoHuber", delta=self.delta)

    def __call__(self, s: Array) -> Array:
        d2 = self.delta**2
        return 2.0 * d2 * (jnp.sqrt(1.0 + s / d2) - 1.0)

    def derivative(self, s: Array) -> Array:
        return 1.0 / jnp.sqrt(1.0 + s / self.delta**2)

    def second_derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        return -0.5 / d2 * (1.0 + s / d2) ** -1.5


class Cauchy(Kernel):
    """ρ(s) = δ² log(1 + s/δ²)."""

    delta: float = 1.0

    def __check_init__(self) -> None:
        _check_positive("Cauchy", delta=self.delta)

    def __call__(self, s: Array) -> Array:
        d2 = self.delta**2
        return d2 * jnp.log1p(s / d2)

    def derivative(self, s: Array) -> Array:
        return 1.0 / (1.0 + s / self.delta**2)

    def second_derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        return -1.0 / (d2 * (1.0 + s / d2) ** 2)


class SoftLOne(Kernel):
    """ρ(s) = 2 (δ √(1/δ² + s) − 1) = 2 (√(1 + δ² s) − 1) (PyPose's definition).

    Note ρ'(0) = δ² (not 1); with δ = 1 it equals ``PseudoHuber(1)``."""

    delta: float = 1.0

    def __check_init__(self) -> None:
        _check_positive("SoftLOne", delta=self.delta)

    def __call__(self, s: Array) -> Array:
        return 2.0 * (jnp.sqrt(1.0 + self.delta**2 * s) - 1.0)

    def derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        return d2 / jnp.sqrt(1.0 + d2 * s)

    def second_derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        return -0.5 * d2 * d2 * (1.0 + d2 * s) ** -1.5


class Arctan(Kernel):
    """ρ(s) = δ² arctan(s/δ²) (bounded by πδ²/2)."""

    delta: float = 1.0

    def __check_init__(self) -> None:
        _check_positive("Arctan", delta=self.delta)

    def __call__(self, s: Array) -> Array:
        d2 = self.delta**2
        return d2 * jnp.arctan(s / d2)

    def derivative(self, s: Array) -> Array:
        u = s / self.delta**2
        return 1.0 / (1.0 + u * u)

    def second_derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        u = s / d2
        return -2.0 * u / (d2 * (1.0 + u * u) ** 2)


class Tolerant(Kernel):
    """ρ(s) = b log(1 + e^{(s−a)/b}) − b log(1 + e^{−a/b}), so ρ'(s) = σ((s − a)/b).

    ``b > 0`` is Ceres' TolerantLoss (ρ' ≈ 0 for s ≪ a: small errors are tolerated,
    linear cost s − a beyond); ``b < 0`` (PyPose's default) gives a saturating cost
    (ρ' ≈ 1 for s ≪ a, → 0 beyond a). ``a ≥ 0``, ``b ≠ 0``; ρ'(0) = σ(−a/b)."""

    a: float = 1.0
    b: float = -1.0

    def __check_init__(self) -> None:
        if isinstance(self.a, (int, float)) and self.a < 0:
            raise ValueError(f"Tolerant(a={self.a!r}): a has to be non-negative")
        if isinstance(self.b, (int, float)) and self.b == 0:
            raise ValueError("Tolerant(b=0): b has to be non-zero")

    def __call__(self, s: Array) -> Array:
        a, b = self.a, self.b
        offset = b * jax.nn.softplus(jnp.asarray(-a / b, jnp.result_type(s)))
        return b * jax.nn.softplus((s - a) / b) - offset

    def derivative(self, s: Array) -> Array:
        return jax.nn.sigmoid((s - self.a) / self.b)

    def second_derivative(self, s: Array) -> Array:
        sig = jax.nn.sigmoid((s - self.a) / self.b)
        return sig * (1.0 - sig) / self.b


class Scale(Kernel):
    """ρ(s) = δ · s (a constant weight; ρ'(s) = δ)."""

    delta: float = 1.0

    def __check_init__(self) -> None:
        _check_positive("Scale", delta=self.delta)

    def __call__(self, s: Array) -> Array:
        return self.delta * s

    def derivative(self, s: Array) -> Array:
        return jnp.full_like(s, self.delta)

    def second_derivative(self, s: Array) -> Array:
        return jnp.zeros_like(s)


class Tukey(Kernel):
    """Tukey's biweight: ρ(s) = (δ²/3)(1 − (1 − s/δ²)³) for s ≤ δ², δ²/3 beyond.

    ρ'(s) = (1 − s/δ²)² inside, 0 outside (outliers are ignored entirely)."""

    delta: float = 1.0

    def __check_init__(self) -> None:
        _check_positive("Tukey", delta=self.delta)

    def __call__(self, s: Array) -> Array:
        d2 = self.delta**2
        u = jnp.minimum(s / d2, 1.0)
        return d2 / 3.0 * (1.0 - (1.0 - u) ** 3)

    def derivative(self, s: Array) -> Array:
        u = s / self.delta**2
        return jnp.where(u <= 1.0, (1.0 - jnp.minimum(u, 1.0)) ** 2, 0.0)

    def second_derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        u = s / d2
        return jnp.where(u <= 1.0, -2.0 / d2 * (1.0 - jnp.minimum(u, 1.0)), 0.0)


class GemanMcClure(Kernel):
    """ρ(s) = δ² s / (δ² + s) (bounded by δ²; GTSAM's GemanMcClure × 2)."""

    delta: float = 1.0

    def __check_init__(self) -> None:
        _check_positive("GemanMcClure", delta=self.delta)

    def __call__(self, s: Array) -> Array:
        d2 = self.delta**2
        return d2 * s / (d2 + s)

    def derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        return (d2 / (d2 + s)) ** 2

    def second_derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        return -2.0 * d2 * d2 / (d2 + s) ** 3


class Welsch(Kernel):
    """ρ(s) = δ² (1 − exp(−s/δ²)) (Welsch / Leclerc; bounded by δ²)."""

    delta: float = 1.0

    def __check_init__(self) -> None:
        _check_positive("Welsch", delta=self.delta)

    def __call__(self, s: Array) -> Array:
        d2 = self.delta**2
        return -d2 * jnp.expm1(-s / d2)

    def derivative(self, s: Array) -> Array:
        return jnp.exp(-s / self.delta**2)

    def second_derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        return -jnp.exp(-s / d2) / d2


__all__ = [
    "Kernel",
    "Trivial",
    "Huber",
    "PseudoHuber",
    "Cauchy",
    "SoftLOne",
    "Arctan",
    "Tolerant",
    "Scale",
    "Tukey",
    "GemanMcClure",
    "Welsch",
]
