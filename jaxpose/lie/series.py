"""Small-angle-safe scalar functions used by the Lie groups.

Every function here is an even function of an angle ``θ`` and is evaluated from
``t = θ²`` (so callers never take ``sqrt`` at zero, whose derivative is infinite).
Each one switches between a closed form and its Taylor series in ``t``:

* the switch point ``t0`` is chosen where the closed form stops losing digits to
  cancellation (typically ``θ ≈ 1``), not at machine epsilon;
* the Taylor coefficients are exact rationals derived below with a tiny
  power-series algebra over :class:`fractions.Fraction`, and the series is truncated
  per dtype where the next term falls below ``1e-18`` (float64) or ``1e-9`` (float32)
  relative at ``t0``, so it is exact to the dtype's precision on the whole series branch
  (float32 needs about half the terms, which also halves compile and run time);
* the switch uses the double-``where`` pattern: each branch only ever sees inputs
  where it is finite, so values and derivatives of any order are NaN-free.

These are the derivative-safe formulas; ``quaternion.exp`` / ``quaternion.log`` take their
values from plain sin/cos/atan2 and only their derivatives from here (see
``docs/numerics.md``). Transcendental functions are evaluated without libm calls:
XLA:CPU lowers ``sin``, ``cos`` and ``atan2`` to scalar calls (10-40 ns per element)
while ``+ × ÷ √`` vectorise (about 1 ns). :func:`sincos` is a Cody–Waite range
reduction plus the same truncated Taylor polynomials, with a ``custom_jvp`` (d sin = cos,
d cos = −sin, any order); :func:`quat_log_coeff` is the quaternion logarithm's
``2·atan2(n, w)/n`` from three half-angle steps and a short ``atan(x)/x`` series,
branch-free.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from fractions import Fraction
from typing import Any

import jax
import jax.numpy as jnp

from ._base import parts

Array = jnp.ndarray

_ORDER = 64  # power-series coefficients (in θ) kept while deriving: enough for 8 derivatives
_LONG = 120  # for the polynomial forms on θ ≤ π (and their derivatives), which need more


# ----------------------------------------------------------------------------------
# Exact power series in θ (lists of Fractions, index = power of θ)
# ----------------------------------------------------------------------------------
def _factorial(n: int) -> int:
    out = 1
    for k in range(2, n + 1):
        out *= k
    return out


def _sin_series(order: int = _ORDER) -> list[Fraction]:
    return [
        Fraction((-1) ** (k // 2), _factorial(k)) if k % 2 == 1 else Fraction(0)
        for k in range(order)
    ]


def _cos_series(order: int = _ORDER) -> list[Fraction]:
    return [
        Fraction((-1) ** (k // 2), _factorial(k)) if k % 2 == 0 else Fraction(0)
        for k in range(order)
    ]


def _mono(power: int, coeff: Fraction | int = 1, order: int = _ORDER) -> list[Fraction]:
    out = [Fraction(0)] * order
    out[power] = Fraction(coeff)
    return out


def _add(*series: list[Fraction]) -> list[Fraction]:
    return [sum(terms, Fraction(0)) for terms in zip(*series, strict=True)]


def _scale(a: list[Fraction], c: Fraction | int) -> list[Fraction]:
    return [Fraction(c) * x for x in a]


def _mul(a: list[Fraction], b: list[Fraction]) -> list[Fraction]:
    out = [Fraction(0)] * len(a)
    for i, x in enumerate(a):
        if x:
            for j in range(len(a) - i):
                out[i + j] += x * b[j]
    return out


def _div(a: list[Fraction], b: list[Fraction]) -> list[Fraction]:
    """Power-series quotient a / b (b[0] must be non-zero)."""
    nonzero = [(i, c) for i, c in enumerate(b) if i and c]
    out = [Fraction(0)] * len(a)
    for k in range(len(a)):
        acc = a[k] - sum((c * out[k - i] for i, c in nonzero if i <= k), Fraction(0))
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


# relative size, at the switch point, of the first dropped Taylor term, per dtype
TRUNCATION = {"float64": 1e-18, "float32": 1e-9}


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
        raise ArithmeticError("series did not converge within the terms derived at t0")
    return tuple(kept)


# ----------------------------------------------------------------------------------
# Evaluation
# ----------------------------------------------------------------------------------
def dtype_key(x: Array) -> str:
    """'float64' for float64 arrays, else 'float32' (float16/bfloat16 use float32 terms)."""
    return "float64" if jnp.asarray(x).dtype == jnp.float64 else "float32"


def horner(coeffs: tuple[float, ...], t: Array) -> Array:
    """Evaluate Σ coeffs[k] tᵏ by Horner's rule (dtype of ``t``)."""
    out = jnp.full_like(t, coeffs[-1])
    for c in coeffs[-2::-1]:
        out = out * t + c
    return out


class Series:
    """Exact rational Taylor coefficients in t with per-dtype truncation at ``t0``."""

    def __init__(self, exact: list[Fraction], t0: float):
        self.exact = exact
        self.t0 = t0
        self.by_dtype = {k: _truncate(exact, t0, rel) for k, rel in TRUNCATION.items()}

    def __call__(self, t: Array) -> Array:
        """Σ cₖ tᵏ with the coefficients truncated for ``t``'s dtype (Horner's rule)."""
        return horner(self.by_dtype[dtype_key(t)], t)


def switched(
    series: Series, direct: Callable[[Array], Array]
) -> Callable[[Array], Array]:
    """t ↦ ``series(t)`` below ``series.t0``, ``direct(t)`` from there on; neither branch
    sees the other's arguments (no overflow or 0/0 in the branch not taken)."""
    t0 = series.t0

    def f(t: Array) -> Array:
        t = jnp.asarray(t)
        small = t < t0
        t_direct = jnp.where(small, jnp.asarray(t0, t.dtype), t)  # direct never sees t < t0
        t_series = jnp.where(small, t, jnp.zeros_like(t))  # series never sees huge t
        return jnp.where(small, series(t_series), direct(t_direct))

    return f


class _Fn:
    """An even scalar function f(θ) evaluated from t = θ² with a series switch (or, with
    ``direct=None``, the series alone: a polynomial for t ≤ t0, the caller's promise).

    Its derivative in t is another :class:`_Fn` (a ``custom_jvp``): the exact rational
    series differentiated term by term, and the autodiff derivative of the closed form.
    Autodiff through the switched Horner polynomial would instead multiply its size by
    about three per derivative order (a Hessian through ``SE3.log`` nests up to five),
    which is what the compiler then has to chew through; the chain f, f′, f″, … grows
    linearly with the order and is created on first use."""

    def __init__(self, name: str, coeffs_t: list[Fraction], t0: float,
                 direct: Callable[[Array], Array] | None, doc: str):
        self.name = name
        self.t0 = t0
        self.exact_coeffs = coeffs_t
        self.series = Series(coeffs_t, t0)
        self.coeffs = self.series.by_dtype["float64"]
        self.direct = direct
        self._derivative: _Fn | None = None
        switched_fn = self.series if direct is None else switched(self.series, direct)
        self._f = jax.custom_jvp(switched_fn)
        self._f.defjvp(self._jvp)
        self.__doc__ = doc

    @classmethod
    def even(cls, name: str, series_theta: list[Fraction], t0: float,
             direct: Callable[[Array], Array], doc: str) -> _Fn:
        """From the power series in θ of an even function."""
        return cls(name, _even_in_t(series_theta), t0, direct, doc)

    @property
    def derivative(self) -> _Fn:
        """d f / d t as an :class:`_Fn` (same switch point)."""
        if self._derivative is None:
            coeffs = [c * (k + 1) for k, c in enumerate(self.exact_coeffs[1:])]
            direct = self.direct

            def direct_dt(t: Array) -> Array:
                return jax.jvp(direct, (t,), (jnp.ones_like(t),))[1]

            self._derivative = _Fn(self.name + "'", coeffs, self.t0,
                                   None if direct is None else direct_dt,
                                   f"d/dt of {self.name}")
        return self._derivative

    def _jvp(self, primals: tuple[Array], tangents: tuple[Array]) -> tuple[Array, Array]:
        (t,), (dt,) = primals, tangents
        f, d = computed_once(self._f(t), self.derivative(t))
        return f, d * dt

    def __call__(self, t: Array) -> Array:
        return self._f(jnp.asarray(t))

    def __repr__(self) -> str:
        return f"series.{self.name}"


def polynomial(fn: _Fn, t0: float) -> _Fn:
    """``fn``'s Taylor series alone, truncated for t ≤ ``t0``, as an :class:`_Fn` (its
    derivatives are the differentiated polynomials): for a caller that switches to its
    own closed form at ``t0``."""
    return _Fn(f"{fn.name}_below_{t0:g}", fn.exact_coeffs, t0, None,
               f"{fn.name} for t ≤ {t0:g} as one polynomial in t.")


# ----------------------------------------------------------------------------------
# sin and cos without libm: Cody–Waite reduction to |r| ≤ π/4 and Taylor polynomials
# ----------------------------------------------------------------------------------
_QUARTER_PI_SQ = (math.pi / 4) ** 2
_SINC_R = Series([Fraction((-1) ** k, _factorial(2 * k + 1)) for k in range(30)], _QUARTER_PI_SQ)
_COS_R = Series([Fraction((-1) ** k, _factorial(2 * k)) for k in range(30)], _QUARTER_PI_SQ)
# π/2 split so that k·part is exact for |k| < 2²⁰ (float64, fdlibm) / 2¹⁵ (float32, Cephes);
# the reduction is then accurate to a few ulp for |x| up to about 1.6e6 / 5e4.
_PIO2_PARTS = {
    "float64": (1.5707963267341256, 6.077100506303966e-11, 2.0222662487959506e-21),
    "float32": (1.5703125, 4.837512969970703125e-4, 7.54978995489188216e-8),
}
SINCOS_EXACT_RANGE = {"float64": 1.6e6, "float32": 5.0e4}


@jax.custom_jvp
def sincos(x: Array) -> tuple[Array, Array]:
    """(sin x, cos x) by range reduction and polynomials (vectorises on every backend).

    Accurate to a few ulp for |x| < ``SINCOS_EXACT_RANGE[dtype]``; beyond that the
    reduction loses about log2(|x|/range) bits, and the results stay bounded by 1 for
    every finite x (meaningless digits, never inf or NaN). Derivatives of any order are exact
    compositions of sin and cos (``custom_jvp``)."""
    x = jnp.asarray(x)
    key = dtype_key(x)
    k = jnp.round(x * (2.0 / math.pi))
    r = x
    for part in _PIO2_PARTS[key]:
        r = r - k * part
    # |r| ≤ π/4 wherever the reduction is exact; far beyond SINCOS_EXACT_RANGE it is not,
    # and the clip keeps |sin|, |cos| ≤ 1 there instead of letting the polynomials explode
    r = jnp.clip(r, -0.8, 0.8)
    r2 = r * r
    sr = r * _SINC_R(r2)
    cr = _COS_R(r2)
    q = k - 4.0 * jnp.floor(0.25 * k)  # quadrant 0..3
    odd = (q == 1.0) | (q == 3.0)
    sin = jnp.where(odd, cr, sr) * jnp.where(q >= 2.0, -1.0, 1.0).astype(x.dtype)
    cos = jnp.where(odd, sr, cr) * jnp.where((q == 1.0) | (q == 2.0), -1.0, 1.0).astype(x.dtype)
    return sin, cos


@sincos.defjvp
def _sincos_jvp(primals: tuple[Array], tangents: tuple[Array]) -> tuple[Any, Any]:
    (x,), (dx,) = primals, tangents
    s, c = sincos(x)
    return (s, c), (c * dx, -s * dx)


def _sin(x: Array) -> Array:
    return sincos(x)[0]


def _cos(x: Array) -> Array:
    return sincos(x)[1]


_SIN, _COS = _sin_series(), _cos_series()

# ----------------------------------------------------------------------------------
# sin θ/θ and cos θ together, with derivatives of any order from one sincos
# ----------------------------------------------------------------------------------
_SINC_T = _even_in_t(_shift(_SIN, 1))  # Σ (−1)ʲ tʲ/(2j+1)!
_COS_SERIES = Series(_even_in_t(_COS), 1.0)


def _sinc_switch(order: int) -> float:
    """Where the ``order``-th derivative of sinc switches from its series to the
    recurrence: t = 1 up to the second; later for higher orders, where the recurrence
    would lose digits near t = 1 (about 1e-10 relative at the fifth at t = 1)."""
    return 1.0 + 2.0 * max(0, order - 2)


@functools.cache
def _sinc_derivative_series(order: int) -> Series:
    """The Taylor series in t of dᵏ/dtᵏ (sin √t / √t), truncated at its switch point."""
    coeffs = _SINC_T
    for _ in range(order):
        coeffs = [c * (k + 1) for k, c in enumerate(coeffs[1:])]
    return Series(coeffs, _sinc_switch(order))


def _switch(t: Array, t0: float, series: Series, direct: Array) -> Array:
    """``series(t)`` below ``t0``, ``direct`` (computed for t ≥ 1) from there on; the
    series never sees a large t."""
    small = t < t0
    return jnp.where(small, series(jnp.where(small, t, jnp.zeros_like(t))), direct)


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _sinc_cos_jet(t: Array, order: int) -> tuple[Array, ...]:
    """(C, S, S′, …, S⁽ᵒʳᵈᵉʳ⁾) at t = θ², C = cos θ, S = sin θ / θ, derivatives in t.

    Below t = 1 (later for S's higher derivatives, :func:`_sinc_switch`) each is its exact
    Taylor series; from there on one :func:`sincos` gives C and S, S′ = (C − S)/(2t), and
    the higher derivatives follow from S's differential equation 4t·S″ + 6S′ + S = 0,
    differentiated k times: S⁽ᵏ⁺²⁾ = −((4k + 6)·S⁽ᵏ⁺¹⁾ + S⁽ᵏ⁾)/(4t). Its jvp is this
    function one order higher (C′ = −S/2), so every derivative order costs one sincos,
    not one per function and order."""
    t = jnp.asarray(t)
    t_direct = jnp.where(t < 1.0, jnp.ones_like(t), t)
    u = jnp.sqrt(t_direct)
    sin_u, cos_u = sincos(u)
    direct = [sin_u / u]
    if order >= 1:
        direct.append((cos_u - direct[0]) / (2.0 * t_direct))
    for k in range(order - 1):
        direct.append(-((4 * k + 6) * direct[-1] + direct[-2]) / (4.0 * t_direct))
    return (_switch(t, 1.0, _COS_SERIES, cos_u),
            *(_switch(t, _sinc_switch(k), _sinc_derivative_series(k), d)
              for k, d in enumerate(direct)))


@_sinc_cos_jet.defjvp
def _sinc_cos_jet_jvp(order: int, primals: tuple[Array], tangents: tuple[Array]) -> Any:
    (t,), (dt,) = primals, tangents
    out = computed_once(*_sinc_cos_jet(t, order + 1))
    return out[:-1], (-0.5 * out[1] * dt, *(f * dt for f in out[2:]))


def sinc_cos(t: Array) -> tuple[Array, Array]:
    """(sin θ / θ, cos θ) from t = θ² (t ≥ 0): the values of :data:`sinc` and :data:`cos`,
    evaluated together — their derivatives of every order share one :func:`sincos`
    (the jvp of SO(3)'s Exp: 842 → 361 operations against the two evaluated apart)."""
    c, s = _sinc_cos_jet(jnp.asarray(t), 0)
    return s, c


_ONE = _mono(0)
_THETA = _mono(1)


def _sqrt(t: Array) -> Array:
    return jnp.sqrt(t)


sinc = _Fn.even(
    "sinc", _shift(_SIN, 1), 1.0,
    lambda t: _sin(_sqrt(t)) / _sqrt(t),
    "sin θ / θ, from t = θ².",
)
cos = _Fn.even(
    "cos", _COS, 1.0,
    lambda t: _cos(_sqrt(t)),
    "cos θ, from t = θ² (smooth in t at 0, unlike cos(sqrt(t)) under autodiff).",
)
one_minus_cos_over_t = _Fn.even(
    "one_minus_cos_over_t", _shift(_add(_ONE, _scale(_COS, -1)), 2), 1.0,
    lambda t: 2.0 * _sin(0.5 * _sqrt(t)) ** 2 / t,
    "(1 − cos θ) / θ²: the first coefficient of the SO(3) Jacobians.",
)
theta_minus_sin_over_theta3 = _Fn.even(
    "theta_minus_sin_over_theta3", _shift(_add(_THETA, _scale(_SIN, -1)), 3), 1.0,
    lambda t: (_sqrt(t) - _sin(_sqrt(t))) / (t * _sqrt(t)),
    "(θ − sin θ) / θ³: the second coefficient of the SO(3) Jacobians.",
)


def _half_cot(order: int) -> list[Fraction]:
    """(θ/2)·cot(θ/2) = cos(θ/2) / sinc(θ/2)."""
    return _div(_substitute_half(_cos_series(order)),
                _substitute_half(_shift(_sin_series(order), 1)))


_HALF_COT_LONG = _half_cot(_LONG)
_HALF_COT = _HALF_COT_LONG[:_ORDER]  # a quotient's leading terms do not depend on its length
jinv_coeff = _Fn.even(
    "jinv_coeff", _shift(_add(_ONE, _scale(_HALF_COT, -1)), 2), 2.25,
    lambda t: 1.0 / t
    - _cos(0.5 * _sqrt(t)) / (2.0 * _sqrt(t) * _sin(0.5 * _sqrt(t))),
    "(1 − (θ/2)cot(θ/2)) / θ²: the quadratic coefficient of J⁻¹ on SO(3) "
    "(singular only at θ = 2π).",
)
jinv_coeff_principal = _Fn.even(
    "jinv_coeff_principal",
    _shift(_add(_mono(0, 1, _LONG), _scale(_HALF_COT_LONG, -1)), 2),
    math.pi**2 * 1.001,
    None,
    "jinv_coeff for θ ≤ π (the range of the logarithm) as one polynomial in t: no closed "
    "form, no switch (the series converges up to θ = 2π; about 31 terms in float64).",
)
half_cot_half = _Fn.even(
    "half_cot_half", _HALF_COT, 1.0,
    lambda t: 0.5 * _sqrt(t) * _cos(0.5 * _sqrt(t)) / _sin(0.5 * _sqrt(t)),
    "(θ/2)·cot(θ/2): the diagonal of the inverse SE(2) V-matrix.",
)
half_cot_half_principal = _Fn.even(
    "half_cot_half_principal", _HALF_COT_LONG, math.pi**2 * 1.001, None,
    "half_cot_half for |θ| ≤ π (the range of the SE(2) logarithm) as one polynomial in t.",
)
half_cot_half_minus_one_over_t_principal = _Fn(
    "half_cot_half_minus_one_over_t_principal", half_cot_half_principal.exact_coeffs[1:],
    math.pi**2 * 1.001, None,
    "((θ/2)·cot(θ/2) − 1)/θ² for |θ| ≤ π as one polynomial in t: SE(2)'s Jl⁻¹ column is "
    "−θ·(this)·ρ − ½·[ρy, −ρx].",
)
se3_q_c2 = _Fn.even(
    "se3_q_c2",
    _scale(_shift(_add(_mono(2), _scale(_COS, 2), _mono(0, -2)), 4), Fraction(1, 2)),
    2.25,
    lambda t: (t + 2.0 * _cos(_sqrt(t)) - 2.0) / (2.0 * t * t),
    "(θ² + 2cos θ − 2) / (2θ⁴): a coefficient of the SE(3) Jacobian's Q block.",
)
se3_q_c3 = _Fn.even(
    "se3_q_c3",
    _scale(
        _shift(_add(_mono(1, 2), _scale(_SIN, -3), _mul(_THETA, _COS)), 5), Fraction(1, 2)
    ),
    4.0,
    lambda t: (2.0 * _sqrt(t) - 3.0 * _sin(_sqrt(t)) + _sqrt(t) * _cos(_sqrt(t)))
    / (2.0 * t * t * _sqrt(t)),
    "(2θ − 3 sin θ + θ cos θ) / (2θ⁵): a coefficient of the SE(3) Jacobian's Q block.",
)

# The SE(2) Jacobian coefficients on the logarithm's range θ ≤ π as one polynomial each:
# they are entire functions, so 10-16 terms in t reach float64 precision at π² (a third of
# the operations of the switched form, which also evaluates the closed form's sin and cos).
one_minus_cos_over_t_principal = _Fn.even(
    "one_minus_cos_over_t_principal", _shift(_add(_ONE, _scale(_COS, -1)), 2),
    math.pi**2 * 1.001, None,
    "one_minus_cos_over_t for θ ≤ π as one polynomial in t.",
)
theta_minus_sin_over_theta3_principal = _Fn.even(
    "theta_minus_sin_over_theta3_principal", _shift(_add(_THETA, _scale(_SIN, -1)), 3),
    math.pi**2 * 1.001, None,
    "theta_minus_sin_over_theta3 for θ ≤ π as one polynomial in t.",
)

# SE(3)'s Jl⁻¹ for |φ| ≤ π as I − ½·ad + β·ad² + γ·ad⁴: ad's minimal polynomial
# x(x² + θ²)² reduces the even part of the Bernoulli series x/(eˣ − 1) to degree 4 (matching
# its value and derivative at ±iθ). With a(t) = (θ/2)cot(θ/2) − 1 = Σ aₖtᵏ:
# β = (t·a′ − 2a)/t and γ = (t·a′ − a)/t² (poles at θ = 2π, like jinv_coeff).
_HALF_COT_MINUS_ONE_T = _even_in_t(_add(_HALF_COT_LONG, _scale(_mono(0, 1, _LONG), -1)))
se3_jinv_ad2_principal = _Fn(
    "se3_jinv_ad2_principal",
    [(k - 2) * c for k, c in enumerate(_HALF_COT_MINUS_ONE_T) if k >= 1],
    math.pi**2 * 1.001, None,
    "β(θ), the ad² coefficient of SE(3)'s Jl⁻¹ for θ ≤ π, as one polynomial in t.",
)
se3_jinv_ad4_principal = _Fn(
    "se3_jinv_ad4_principal",
    [(k - 1) * c for k, c in enumerate(_HALF_COT_MINUS_ONE_T) if k >= 2],
    math.pi**2 * 1.001, None,
    "γ(θ), the ad⁴ coefficient of SE(3)'s Jl⁻¹ for θ ≤ π, as one polynomial in t.",
)

# atan(x)/x as a function of s = x²: the series converges for s < 1, and is kept to
# s < 0.04 (≥ 1e-18 relative in 13 terms); larger arguments are brought there by the
# half-angle identity atan(x) = 2·atan(x / (1 + √(1 + x²))), branch-free.
_ATAN_T0 = 0.04
_ATAN = Series([Fraction((-1) ** k, 2 * k + 1) for k in range(80)], _ATAN_T0)
_ATAN_COEFFS = _ATAN.by_dtype["float64"]


def _atanc_halved(s: Array, steps: int) -> Array:
    """atan(x)/x from s = x² after ``steps`` half-angle steps (each halves atan(x), so
    ``steps`` = 3 covers every s ≥ 0 and 2 covers s ≤ 1). Smooth in s ≥ 0."""
    scale = jnp.ones_like(s)
    for _ in range(steps):
        g = 1.0 / (1.0 + jnp.sqrt(1.0 + s))  # tan(α/2) = tan α · g
        s = s * g * g
        scale = scale * (2.0 * g)
    return scale * _ATAN(s)


def atanc(s: Array) -> Array:
    """atan(x) / x from s = x² (s ≥ 0), branch-free (no atan call)."""
    return _atanc_halved(jnp.asarray(s), 3)


@jax.custom_jvp
def quat_log_coeff(n2: Array, w: Array) -> Array:
    """2·atan2(n, w) / n from n² = |v|² and w ≥ 0: the factor that maps the vector part
    v of a quaternion (v, w) to its rotation vector. Exact at n = 0 (value 2/w) and at
    w = 0 (π/n), with finite derivatives of any order wherever n² + w² > 0.

    With d = √(n² + w²) + w (no cancellation for w ≥ 0), atan2(n, w) = 2·atan(n/d) and
    n/d ≤ 1, so two more half-angle steps reach the series range. Its partial derivatives
    are closed forms (``custom_jvp``, see :func:`_quat_log_coeff_jvp`), so higher orders
    differentiate those instead of the half-angle chain."""
    d = jnp.sqrt(n2 + w * w) + w
    return 4.0 / d * _atanc_halved(n2 / (d * d), 2)


# K(s) = (atan(√s)/√s − 1/(1+s)) / s = Σ_j (−1)^j (2j+2)/(2j+3) s^j, kept to s < 0.04
_LOG_DN2 = _Fn("log_dn2", [Fraction((-1) ** j * (2 * j + 2), 2 * j + 3) for j in range(60)],
              _ATAN_T0, None, "K(s) for s ≤ 0.04, one polynomial (derivatives term-wise).")


@quat_log_coeff.defjvp
def _quat_log_coeff_jvp(primals: tuple[Array, Array],
                        tangents: tuple[Array, Array]) -> tuple[Array, Array]:
    """f = 2·atan2(n, w)/n: ∂f/∂w = −2/r² (r² = n² + w²) and ∂f/∂n² = −(f/2 − w/r²)/n²,
    which is −K(n²/w²)/w³ by a series where n² < 0.04·w² (the closed form cancels there)."""
    (n2, w), (dn2, dw) = primals, tangents
    f = quat_log_coeff(n2, w)
    r2 = n2 + w * w
    small = n2 < _ATAN_T0 * w * w  # implies w ≠ 0
    n2_direct = jnp.where(small, jnp.ones_like(n2), n2)
    w_series = jnp.where(small, w, jnp.ones_like(w))
    s = jnp.where(small, n2 / (w_series * w_series), jnp.zeros_like(n2))
    d_n2 = jnp.where(small, -_LOG_DN2(s) / (w_series * w_series * w_series),
                     -(0.5 * f - w / r2) / n2_direct)
    f, d_n2, d_w = computed_once(f, d_n2, -2.0 / r2)
    return f, d_n2 * dn2 + d_w * dw


_EXPM1C = Series([Fraction(1, _factorial(k + 1)) for k in range(40)], 1.0)


def expm1c(x: Array) -> Array:
    """(eˣ − 1) / x for any real x (not an even function: the argument is x itself).

    Taylor series for |x| < 1, where the autodiff derivatives of the closed form would
    lose up to 1/|x|ⁿ digits to cancellation; the closed form elsewhere."""
    x = jnp.asarray(x)
    small = jnp.abs(x) < 1.0
    x_direct = jnp.where(small, jnp.ones_like(x), x)
    x_series = jnp.where(small, x, jnp.zeros_like(x))
    return jnp.where(small, _EXPM1C(x_series), jnp.expm1(x_direct) / x_direct)


def computed_once(*xs: Array) -> tuple[Array, ...]:
    """The arrays ``xs`` (broadcast to one shape) unchanged, each computed once. XLA:CPU
    fuses a cheap elementwise chain (a Horner polynomial) into each consumer and evaluates
    it once per element: a coefficient broadcast over a 6×6 block ran 36 times (SE(3)'s
    Jr⁻¹ 7x slower), and the series' derivative rules below, whose coefficients every
    derivative order consumes, were copied into a dozen fusions of a gradient through a
    solve. A product with the identity is a dot, which XLA neither fuses nor simplifies
    away (``jax.lax.optimization_barrier`` is removed before fusion on CPU); it is exact
    for finite values. One array goes in twice (XLA simplifies a 1×1 dot into a
    product)."""
    lanes = xs if len(xs) > 1 else (xs[0], xs[0])
    stacked = jnp.stack(jnp.broadcast_arrays(*lanes), -1)
    out = jnp.matmul(stacked, jnp.eye(len(lanes), dtype=stacked.dtype),
                     precision=jax.lax.Precision.HIGHEST)
    return tuple(parts(out)[:len(xs)])


def safe_norm_sq(v: Array, axis: int = -1) -> Array:
    """Σ v² along ``axis`` (smooth everywhere, unlike the norm). Short axes are summed
    component by component: XLA:CPU emits a slow reduction loop for a 3- or 4-wide axis."""
    v = jnp.asarray(v)
    n = v.shape[axis] if v.ndim else 0
    if 0 < n <= 8:
        cs = parts(v, axis)
        out = cs[0] * cs[0]
        for p in cs[1:]:
            out = out + p * p
        return out
    return jnp.sum(v * v, axis=axis)


ALL = (
    sinc, cos, one_minus_cos_over_t, theta_minus_sin_over_theta3, jinv_coeff,
    half_cot_half, se3_q_c2, se3_q_c3,
)
# the same functions as polynomials on the logarithms' range θ ≤ π
PRINCIPAL = {
    jinv_coeff: jinv_coeff_principal,
    half_cot_half: half_cot_half_principal,
    one_minus_cos_over_t: one_minus_cos_over_t_principal,
    theta_minus_sin_over_theta3: theta_minus_sin_over_theta3_principal,
}


# polynomials on θ ≤ π without a general (switched) form
AD_PRINCIPAL = (se3_jinv_ad2_principal, se3_jinv_ad4_principal)


def select(fn: _Fn, principal: bool) -> _Fn:
    """``fn``, or with ``principal=True`` (the caller promises θ ≤ π) its polynomial form
    ``PRINCIPAL[fn]``."""
    return PRINCIPAL[fn] if principal else fn
