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
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._safe import safe_sqrt

Array = jax.Array


def _is_traced(val: Any) -> bool:
    return isinstance(val, jax.core.Tracer)


def _check_param(name: str, key: str, val: Any, ok: Callable[[Any], Any], what: str) -> None:
    """ValueError unless ``ok(val)`` holds everywhere, for a value known at construction
    (Python or NumPy numbers, NumPy and concrete JAX arrays); traced values are checked at
    run time by ``Kernel._checked``."""
    if _is_traced(val):
        return
    try:
        arr = np.asarray(val)
        good = bool(np.all(ok(arr)))
    except TypeError as err:
        raise TypeError(f"{name}({key}={val!r}): expected a number") from err
    if not good:
        shown = val if isinstance(val, (int, float)) else arr
        raise ValueError(f"{name}({key}={shown!r}): {key} has to be {what}")


# a parameter name -> (the condition on its value, what is expected)
Constraints = dict[str, tuple[Callable[[Any], Any], str]]
_POSITIVE_DELTA: Constraints = {"delta": (lambda v: v > 0, "positive")}


class Kernel(eqx.Module):
    """Base class: ρ(s) with analytic first and second derivatives.

    Parameters with a domain (``delta > 0``; Tolerant's ``a ≥ 0``, ``b ≠ 0``) are checked
    on construction when their value is known (Python or NumPy numbers, NumPy and concrete
    JAX arrays: ValueError naming the parameter); traced ones (``Huber(d)`` inside
    ``jit``/``grad``/``vmap``) by :func:`~jaxpose.optim.least_squares` at run time."""

    _constraints: ClassVar[Constraints] = {}

    def __check_init__(self) -> None:
        for key, (ok, what) in self._constraints.items():
            _check_param(type(self).__name__, key, getattr(self, key), ok, what)

    def _checked(self) -> Kernel:
        """This kernel with its traced parameters checked at run time (``eqx.error_if``,
        also under ``jit``/``vmap``) and its known ones now (ValueError: construction
        checked them, but ``eqx.tree_at`` can put a new value in without it)."""
        out = self
        for key, (ok, what) in self._constraints.items():
            val = getattr(self, key)
            if not _is_traced(val):
                _check_param(type(self).__name__, key, val, ok, what)
            else:
                val = eqx.error_if(val, ~jnp.all(ok(val)),
                                   f"{type(self).__name__}({key}): {key} has to be {what}")
                out = eqx.tree_at(lambda k, key=key: getattr(k, key), out, val)
        return out

    def _in_dtype(self, dtype: Any) -> Kernel:
        """This kernel with its array parameters (NumPy or JAX; Python floats are weakly
        typed already) cast to ``dtype``, the residuals' dtype, as information matrices
        are: a float64 ``np.sqrt(chi2_quantile(...))`` must not turn a float32 problem's
        cost into float64 (a solver-loop carry type error)."""
        def cast(v: Any) -> Any:
            if isinstance(v, (np.ndarray, np.generic, jax.Array)) and jnp.issubdtype(
                    jnp.result_type(v), jnp.floating):
                return jnp.asarray(v, dtype)
            return v

        return jax.tree.map(cast, self)

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

    _constraints = _POSITIVE_DELTA

    def __call__(self, s: Array) -> Array:
        d = self.delta
        inner = s <= d * d
        return jnp.where(inner, s, 2.0 * d * safe_sqrt(jnp.where(inner, d * d, s)) - d * d)

    def derivative(self, s: Array) -> Array:
        d = self.delta
        inner = s <= d * d
        return jnp.where(inner, 1.0, d / safe_sqrt(jnp.where(inner, 1.0, s)))

    def second_derivative(self, s: Array) -> Array:
        d = self.delta
        inner = s <= d * d
        so = jnp.where(inner, 1.0, s)
        return jnp.where(inner, 0.0, -0.5 * d / (so * jnp.sqrt(so)))


class PseudoHuber(Kernel):
    """ρ(s) = 2δ² (√(1 + s/δ²) − 1), a smooth Huber."""

    delta: float = 1.0

    _constraints = _POSITIVE_DELTA

    def __call__(self, s: Array) -> Array:
        # 2δ²(√(1+s/δ²) − 1) without the cancellation (exactly 0 in float32 for s < 1e-7)
        return 2.0 * s / (jnp.sqrt(1.0 + s / self.delta**2) + 1.0)

    def derivative(self, s: Array) -> Array:
        return 1.0 / jnp.sqrt(1.0 + s / self.delta**2)

    def second_derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        return -0.5 / d2 * (1.0 + s / d2) ** -1.5


class Cauchy(Kernel):
    """ρ(s) = δ² log(1 + s/δ²)."""

    delta: float = 1.0

    _constraints = _POSITIVE_DELTA

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

    _constraints = _POSITIVE_DELTA

    def __call__(self, s: Array) -> Array:
        d2s = self.delta**2 * s  # 2(√(1+δ²s) − 1) without the cancellation at small s
        return 2.0 * d2s / (jnp.sqrt(1.0 + d2s) + 1.0)

    def derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        return d2 / jnp.sqrt(1.0 + d2 * s)

    def second_derivative(self, s: Array) -> Array:
        d2 = self.delta**2
        return -0.5 * d2 * d2 * (1.0 + d2 * s) ** -1.5


class Arctan(Kernel):
    """ρ(s) = δ² arctan(s/δ²) (bounded by πδ²/2)."""

    delta: float = 1.0

    _constraints = _POSITIVE_DELTA

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

    _constraints = {"a": (lambda v: v >= 0, "non-negative"), "b": (lambda v: v != 0, "non-zero")}

    def __call__(self, s: Array) -> Array:
        a, b = self.a, self.b
        dtype = jnp.result_type(s)
        x = s / b
        # b·(softplus((s − a)/b) − softplus(−a/b)) = b·log1p(σ(−a/b)·expm1(s/b)): no
        # cancellation at small s; the difference form where expm1 would overflow (the
        # stable form's input clamped, so its unused derivative stays finite)
        near = x < 30.0
        lead = jax.nn.sigmoid(jnp.asarray(-a / b, dtype))
        stable = b * jnp.log1p(lead * jnp.expm1(jnp.minimum(x, 30.0)))
        offset = b * jax.nn.softplus(jnp.asarray(-a / b, dtype))
        return jnp.where(near, stable, b * jax.nn.softplus((s - a) / b) - offset)

    def derivative(self, s: Array) -> Array:
        return jax.nn.sigmoid((s - self.a) / self.b)

    def second_derivative(self, s: Array) -> Array:
        sig = jax.nn.sigmoid((s - self.a) / self.b)
        return sig * (1.0 - sig) / self.b


class Scale(Kernel):
    """ρ(s) = δ · s (a constant weight; ρ'(s) = δ)."""

    delta: float = 1.0

    _constraints = _POSITIVE_DELTA

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

    _constraints = _POSITIVE_DELTA

    def __call__(self, s: Array) -> Array:
        d2 = self.delta**2
        u = jnp.minimum(s / d2, 1.0)
        # 1 − (1 − u)³ expanded where it cancels (small u), as written where the expanded
        # form's derivative would (u near 1: (1 − u)² as 1 − 2u + u²); both accurate
        expanded = u * (3.0 - 3.0 * u + u * u)
        return d2 / 3.0 * jnp.where(u < 0.5, expanded, 1.0 - (1.0 - u) ** 3)

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

    _constraints = _POSITIVE_DELTA

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

    _constraints = _POSITIVE_DELTA

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
