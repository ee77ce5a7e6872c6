"""Small-angle-safe scalar functions used by the Lie groups.

Every function here is an even function of an angle ``θ`` and is evaluated from
``t = θ²`` (so callers never take ``sqrt`` at zero, whose derivative is infinite).
Each one switches between a closed form and its Taylor series in ``t``:

* the switch point ``t0`` is chosen where the closed form stops losing digits to
  cancellation (typically ``θ ≈ 1``), not at machine epsilon;
* the Taylor coefficients are exact rationals derived below with a tiny
  power-series algebra over :class:`fractions.Fraction`, and the series is truncated
  where the next term falls below ``1e-18`` relative at ``t0``, so it is exact to
  float64 (hence float32) precision on the whole series branch;
* the switch uses the double-``where`` pattern: each branch only ever sees inputs
  where it is finite, so values and derivatives of any order are NaN-free.
"""

from __future__ import annotations

from collections.abc import Callable
from fractions import Fraction

import jax.numpy as jnp

Array = jnp.ndarray

_ORDER = 48  # number of power-series coefficients (in θ) kept while deriving


# ----------------------------------------------------------------------------------
# Exact power series in θ (lists of Fractions, index = power of θ)
# ----------------------------------------------------------------------------------
def _factorial(n: int) -> int:
    out = 1
    for k in range(2, n + 1):
        out *= k
    return out


def _sin() -> list[Fraction]:
    return [
        Fraction((-1) ** (k // 2), _factorial(k)) if k % 2 == 1 else Fraction(0)
        for k in range(_ORDER)
    ]


def _cos() -> list[Fraction]:
    return [
        Fraction((-1) ** (k // 2), _factorial(k)) if k % 2 == 0 else Fraction(0)
        for k in range(_ORDER)
    ]


def _mono(power: int, coeff: Fraction | int = 1) -> list[Fraction]:
    out = [Fraction(0)] * _ORDER
    out[power] = Fraction(coeff)
    return out


def _add(*series: list[Fraction]) -> list[Fraction]:
    return [sum(terms, Fraction(0)) for terms in zip(*series, strict=True)]


def _scale(a: list[Fraction], c: Fraction | int) -> list[Fraction]:
    return [Fraction(c) * x for x in a]


def _mul(a: list[Fraction], b: list[Fraction]) -> list[Fraction]:
    out = [Fraction(0)] * _ORDER
    for i, x in enumerate(a):
        if x:
            for j in range(_ORDER - i):
                out[i + j] += x * b[j]
    return out


def _div(a: list[Fraction], b: list[Fraction]) -> list[Fraction]:
    """Power-series quotient a / b (b[0] must be non-zero)."""
    out = [Fraction(0)] * _ORDER
    for k in range(_ORDER):
        acc = a[k] - sum((out[j] * b[k - j] for j in range(k)), Fraction(0))
        out[k] = acc / b[0]
    return out


def _shift(a: list[Fraction], n: int) -> list[Fraction]:
    """Divide by θⁿ; the first n coefficients must vanish."""
    if any(a[:n]):
        raise ArithmeticError("series is not divisible by θ^n")
    return a[n:] + [Fraction(0)] * n


def _substitute_half(a: list[Fraction]) -> list[Fraction]:
    """Series of f(θ/2) from the series of f(θ)."""
    return [x / (2**k) for k, x in enumerate(a)]


def _even_in_t(a: list[Fraction]) -> list[Fraction]:
    """Coefficients in t = θ² of an even series in θ."""
    if any(a[1::2]):
        raise ArithmeticError("series is not even")
    return a[0::2]


def _truncate(coeffs: list[Fraction], t0: float, rel: float = 1e-18) -> tuple[float, ...]:
    """Keep terms until |c_k| t0^k falls below ``rel`` times the leading term."""
    lead = abs(float(coeffs[0])) or 1.0
    kept: list[float] = []
    quiet = 0
    for k, c in enumerate(coeffs):
        kept.append(float(c))
        if abs(float(c)) * t0**k < rel * lead:
            quiet += 1
            if quiet >= 2:
                break
        else:
            quiet = 0
    else:  # pragma: no cover - guards the derivation itself
        raise ArithmeticError("series did not converge within _ORDER terms at t0")
    return tuple(kept)


# ----------------------------------------------------------------------------------
# Evaluation
# ----------------------------------------------------------------------------------
def horner(coeffs: tuple[float, ...], t: Array) -> Array:
    """Evaluate Σ coeffs[k] tᵏ by Horner's rule (dtype of ``t``)."""
    out = jnp.full_like(t, coeffs[-1])
    for c in coeffs[-2::-1]:
        out = out * t + c
    return out


def _switched(
    coeffs: tuple[float, ...], t0: float, direct: Callable[[Array], Array]
) -> Callable[[Array], Array]:
    def f(t: Array) -> Array:
        t = jnp.asarray(t)
        small = t < t0
        t_direct = jnp.where(small, jnp.asarray(t0, t.dtype), t)  # direct never sees t < t0
        t_series = jnp.where(small, t, jnp.zeros_like(t))  # series never sees huge t
        return jnp.where(small, horner(coeffs, t_series), direct(t_direct))

    return f


class _Fn:
    """An even scalar function f(θ) evaluated from t = θ² with a series switch."""

    def __init__(self, name: str, series_theta: list[Fraction], t0: float,
                 direct: Callable[[Array], Array], doc: str):
        self.name = name
        self.t0 = t0
        self.coeffs = _truncate(_even_in_t(series_theta), t0)
        self.exact_coeffs = _even_in_t(series_theta)
        self._f = _switched(self.coeffs, t0, direct)
        self.__doc__ = doc

    def __call__(self, t: Array) -> Array:
        return self._f(t)

    def __repr__(self) -> str:
        return f"series.{self.name}"


_SIN, _COS = _sin(), _cos()
_ONE = _mono(0)
_THETA = _mono(1)


def _sqrt(t: Array) -> Array:
    return jnp.sqrt(t)


sinc = _Fn(
    "sinc", _shift(_SIN, 1), 1.0,
    lambda t: jnp.sin(_sqrt(t)) / _sqrt(t),
    "sin θ / θ, from t = θ².",
)
cos = _Fn(
    "cos", _COS, 1.0,
    lambda t: jnp.cos(_sqrt(t)),
    "cos θ, from t = θ² (smooth in t at 0, unlike cos(sqrt(t)) under autodiff).",
)
one_minus_cos_over_t = _Fn(
    "one_minus_cos_over_t", _shift(_add(_ONE, _scale(_COS, -1)), 2), 1.0,
    lambda t: 2.0 * jnp.sin(0.5 * _sqrt(t)) ** 2 / t,
    "(1 − cos θ) / θ²: the first coefficient of the SO(3) Jacobians.",
)
theta_minus_sin_over_theta3 = _Fn(
    "theta_minus_sin_over_theta3", _shift(_add(_THETA, _scale(_SIN, -1)), 3), 1.0,
    lambda t: (_sqrt(t) - jnp.sin(_sqrt(t))) / (t * _sqrt(t)),
    "(θ − sin θ) / θ³: the second coefficient of the SO(3) Jacobians.",
)
# (θ/2)·cot(θ/2) = cos(θ/2) / sinc(θ/2)
_HALF_COT = _div(_substitute_half(_COS), _substitute_half(_shift(_SIN, 1)))
jinv_coeff = _Fn(
    "jinv_coeff", _shift(_add(_ONE, _scale(_HALF_COT, -1)), 2), 2.25,
    lambda t: 1.0 / t
    - jnp.cos(0.5 * _sqrt(t)) / (2.0 * _sqrt(t) * jnp.sin(0.5 * _sqrt(t))),
    "(1 − (θ/2)cot(θ/2)) / θ²: the quadratic coefficient of J⁻¹ on SO(3) "
    "(singular only at θ = 2π).",
)
half_cot_half = _Fn(
    "half_cot_half", _HALF_COT, 1.0,
    lambda t: 0.5 * _sqrt(t) * jnp.cos(0.5 * _sqrt(t)) / jnp.sin(0.5 * _sqrt(t)),
    "(θ/2)·cot(θ/2): the diagonal of the inverse SE(2) V-matrix.",
)
se3_q_c2 = _Fn(
    "se3_q_c2",
    _scale(_shift(_add(_mono(2), _scale(_COS, 2), _mono(0, -2)), 4), Fraction(1, 2)),
    2.25,
    lambda t: (t + 2.0 * jnp.cos(_sqrt(t)) - 2.0) / (2.0 * t * t),
    "(θ² + 2cos θ − 2) / (2θ⁴): a coefficient of the SE(3) Jacobian's Q block.",
)
se3_q_c3 = _Fn(
    "se3_q_c3",
    _scale(
        _shift(_add(_mono(1, 2), _scale(_SIN, -3), _mul(_THETA, _COS)), 5), Fraction(1, 2)
    ),
    4.0,
    lambda t: (2.0 * _sqrt(t) - 3.0 * jnp.sin(_sqrt(t)) + _sqrt(t) * jnp.cos(_sqrt(t)))
    / (2.0 * t * t * _sqrt(t)),
    "(2θ − 3 sin θ + θ cos θ) / (2θ⁵): a coefficient of the SE(3) Jacobian's Q block.",
)

# atan(x)/x as a function of s = x² (used by the SO(3) logarithm); radius of
# convergence 1, so the series branch is kept to s < 0.04.
_ATAN_T0 = 0.04
_ATAN_COEFFS = _truncate([Fraction((-1) ** k, 2 * k + 1) for k in range(80)], _ATAN_T0)
atanc = _switched(
    _ATAN_COEFFS, _ATAN_T0, lambda s: jnp.arctan(jnp.sqrt(s)) / jnp.sqrt(s)
)
atanc.__doc__ = "atan(x) / x from s = x² (s ≥ 0)."


def expm1c(x: Array) -> Array:
    """(eˣ − 1) / x for any real x (not an even function: the argument is x itself)."""
    x = jnp.asarray(x)
    small = jnp.abs(x) < 1e-2
    x_direct = jnp.where(small, jnp.ones_like(x), x)
    x_series = jnp.where(small, x, jnp.zeros_like(x))
    coeffs = tuple(1.0 / _factorial(k + 1) for k in range(9))
    return jnp.where(small, horner(coeffs, x_series), jnp.expm1(x_direct) / x_direct)


def safe_norm_sq(v: Array, axis: int = -1) -> Array:
    """Σ v² along ``axis`` (smooth everywhere, unlike the norm)."""
    return jnp.sum(v * v, axis=axis)


ALL = (
    sinc, cos, one_minus_cos_over_t, theta_minus_sin_over_theta3, jinv_coeff,
    half_cot_half, se3_q_c2, se3_q_c3,
)
