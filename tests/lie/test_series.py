"""The small-angle-safe scalar functions of ``jaxpose.lie.series`` against mpmath.

For every function (the eight in ``series.ALL``, their polynomial forms on the logarithms'
range θ ≤ π in ``series.PRINCIPAL``, ``atanc`` and ``expm1c``):

* values in float64 and float32 on a log-spaced range and just below / above the switch
  point ``t0``, against the closed form evaluated by mpmath with enough extra digits to
  absorb its cancellation (float32: the float32-rounded argument is fed to the reference);
* the exact rational Taylor coefficients (and the float coefficients actually used) against
  an mpmath Taylor expansion of the closed form, computed independently of the library's
  power-series algebra: the Cauchy integral of the closed form on a circle around 0
  (trapezoidal rule, spectrally accurate for these analytic functions), cross-checked against
  ``mpmath.taylor`` for the leading coefficients;
* first and second derivatives (autodiff) on both sides of the switch: continuous to
  ~1e-12 relative and equal to mpmath's derivative of the closed form; first to third
  derivatives finite at t = 0 and at t0 and equal to mpmath's inside the domain.
"""

from __future__ import annotations

import functools
from fractions import Fraction
from typing import Any

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import mpmath as mp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from _jaxprs import equations  # noqa: E402

from jaxpose.lie import SE2, SE3, series  # noqa: E402
from jaxpose.lie import _quaternion as quat  # noqa: E402
from jaxpose.lie._base import parts  # noqa: E402

from .conftest import FAST_COMPILE  # noqa: E402

DPS = 60  # base working precision of every reference (decimal digits)

# ------------------------------------------------------------------------------------
# references: closed forms in mpmath of the angle θ (t = θ²); work for mpf and mpc
# ------------------------------------------------------------------------------------
def _half_cot_m1(th):
    return (th / 2) * mp.cot(th / 2) - 1


def _ad4(th):  # (θA′ − 2A) / (2θ⁴)
    d = mp.cot(th / 2) / 2 - (th / 4) / mp.sin(th / 2) ** 2
    return (th * d - 2 * _half_cot_m1(th)) / (2 * th**4)


_CLOSED_FORMS = {
    "sinc": lambda th: mp.sin(th) / th,
    "cos": lambda th: mp.cos(th),
    "one_minus_cos_over_t": lambda th: (1 - mp.cos(th)) / th**2,
    "theta_minus_sin_over_theta3": lambda th: (th - mp.sin(th)) / th**3,
    "jinv_coeff": lambda th: (1 - (th / 2) * mp.cot(th / 2)) / th**2,
    "half_cot_half": lambda th: (th / 2) * mp.cot(th / 2),
    "se3_q_c2": lambda th: (th**2 + 2 * mp.cos(th) - 2) / (2 * th**4),
    "se3_q_c3": lambda th: (2 * th - 3 * mp.sin(th) + th * mp.cos(th)) / (2 * th**5),
    # SE(3)'s Jl⁻¹ = I − ½ad + β·ad² + γ·ad⁴ with A = (θ/2)cot(θ/2) − 1 and its derivative A′
    "se3_jinv_ad2_principal": lambda th: (_ad4(th) * th**4 - _half_cot_m1(th)) / th**2,
    "se3_jinv_ad4_principal": _ad4,
    # atanc is a function of s = x² with f = atan(x)/x; expm1c of x itself
    "atanc": lambda x: mp.atan(x) / x,
    "expm1c": lambda x: mp.expm1(x) / x,
}
# every closed form is 0/0-free away from 0; the worst cancellation at angle θ loses about
# 5·|log10 θ| digits (θ⁵ in the denominator), so the reference adds that many.
# the logarithms' polynomial forms (θ ≤ π) are the same functions on a smaller domain
for _general, _principal in series.PRINCIPAL.items():
    _CLOSED_FORMS[_principal.name] = _CLOSED_FORMS[_general.name]
_POLYNOMIALS = (*series.PRINCIPAL.values(), *series.AD_PRINCIPAL)  # forms on θ ≤ π
_EVEN = [fn.name for fn in (*series.ALL, *_POLYNOMIALS)]  # functions of t = θ²
# (name, callable, t0, domain upper bound in t) for the even functions of θ
_FUNCS = {fn.name: (fn, fn.t0) for fn in (*series.ALL, *_POLYNOMIALS)}
_FUNCS["atanc"] = (series.atanc, series._ATAN_T0)


class _SincCosPart:
    """One output of :func:`series.sinc_cos` (index 0: sinc, 1: cos) as a function of t,
    with the Taylor coefficients of the function it computes, so that every test below
    applies to it as to the :class:`series._Fn` of that name."""

    def __init__(self, index: int, like):
        self.index, self.name = index, f"sinc_cos[{index}]"
        self.exact_coeffs, self.coeffs, self.t0 = like.exact_coeffs, like.coeffs, like.t0

    def __call__(self, t):
        return series.sinc_cos(t)[self.index]


for _i, _like in enumerate((series.sinc, series.cos)):
    _part = _SincCosPart(_i, _like)
    _FUNCS[_part.name] = (_part, _part.t0)
    _CLOSED_FORMS[_part.name] = _CLOSED_FORMS[_like.name]
    _EVEN.append(_part.name)
# radius of convergence in θ (or x): cot(θ/2) has poles at ±2π, atan(x)/x branch points at ±i
_RADIUS = {"jinv_coeff": 2 * np.pi, "half_cot_half": 2 * np.pi, "atanc": 1.0}
# largest t at which each function is tested (cot-based ones blow up at θ = 2π)
_T_MAX = {"jinv_coeff": 30.0, "half_cot_half": 30.0, "atanc": 1e4,
          **{fn.name: fn.t0 for fn in _POLYNOMIALS}}
for _general, _principal in series.PRINCIPAL.items():
    if _general.name in _RADIUS:  # the others are entire
        _RADIUS[_principal.name] = _RADIUS[_general.name]
for _fn in series.AD_PRINCIPAL:
    _RADIUS[_fn.name] = 2 * np.pi

F64_TOL = 1e-14
F32_TOL = 2e-6
DERIV_CONT_TOL = 1e-12


def _extra_digits(x: float) -> int:
    return 10 + int(5 * max(0.0, -np.log10(abs(x)))) if x != 0 else 0


def ref_value(name: str, t: float) -> float:
    """f(t) (or f(x) for expm1c) correctly rounded to float64 from mpmath."""
    f = _CLOSED_FORMS[name]
    if name == "expm1c":
        if t == 0:
            return 1.0
        with mp.workdps(DPS + _extra_digits(t)):
            return float(f(mp.mpf(t)))
    if t == 0:
        return float(_exact_coeffs(name)[0])
    with mp.workdps(DPS + _extra_digits(t)):
        return float(f(mp.sqrt(mp.mpf(t))))


def ref_derivative(name: str, t: float, n: int) -> float:
    """n-th derivative in t (in x for expm1c) by mpmath's numerical differentiation."""
    f = _CLOSED_FORMS[name]
    g = (lambda u: f(u)) if name == "expm1c" else (lambda u: f(mp.sqrt(u)))
    with mp.workdps(DPS + 30):
        return float(mp.diff(g, mp.mpf(t), n))


def _exact_coeffs(name: str) -> list[Fraction]:
    if name == "atanc":
        return [Fraction((-1) ** k, 2 * k + 1) for k in range(len(series._ATAN_COEFFS) + 2)]
    return list(_FUNCS[name][0].exact_coeffs)


@functools.cache
def cauchy_taylor(name: str, n_terms: int) -> tuple:
    """Coefficients c_k of f = Σ c_k θ^k by the trapezoidal rule for the Cauchy integral
    c_k = (1 / 2πi) ∮ f(z) z^{-k-1} dz on |z| = r (mpmath, 80 digits)."""
    f = _CLOSED_FORMS[name]
    r = mp.mpf(min(2.0, 0.5 * _RADIUS.get(name, np.inf)))
    n_nodes = 160
    with mp.workdps(80):
        zs = [r * mp.expjpi(mp.mpf(2 * j) / n_nodes) for j in range(n_nodes)]
        fz = [f(z) for z in zs]
        out = []
        for k in range(n_terms):
            acc = mp.fsum(fz[j] * mp.expjpi(-mp.mpf(2 * j * k) / n_nodes) for j in range(n_nodes))
            out.append(mp.re(acc) / n_nodes / r**k)
        return tuple(out)


def _jfun(name: str):
    if name == "expm1c":
        return series.expm1c
    return _FUNCS[name][0]


ALL_NAMES = [*_EVEN, "atanc", "expm1c"]


def _switch_points(name: str) -> list[float]:
    if name == "expm1c":
        return [-1e-2, 1e-2]
    return [_FUNCS[name][1]]


def _sample_args(name: str) -> np.ndarray:
    """Log-spaced arguments plus a cluster around every switch point."""
    if name == "expm1c":
        mag = np.logspace(-12, np.log10(30.0), 40)
        base = np.concatenate([mag, -mag, [0.0]])
    else:
        base = np.concatenate([[0.0], np.logspace(-24, np.log10(_T_MAX.get(name, 30.0)), 50)])
    near = [
        s * (1 + d) for s in _switch_points(name) for d in
        (-1e-3, -1e-6, -1e-12, -2.0**-52, 0.0, 2.0**-52, 1e-12, 1e-6, 1e-3)
    ]
    return np.unique(np.concatenate([base, near]))


# ------------------------------------------------------------------------------------
# values
# ------------------------------------------------------------------------------------
@functools.cache
def _reference_table(name: str, dtype_name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arguments (rounded to the dtype first), reference values and error scales.

    The scale is max(|f|, |θ·df/dθ|): cos, sinc and (θ/2)cot(θ/2) cross zero inside the
    tested range, where any evaluation through θ = √t (rounded) has an absolute error of
    about |θ f'(θ)|·ε; elsewhere the scale is |f| and the error is the plain relative one."""
    args = _sample_args(name).astype(dtype_name)
    refs = np.array([ref_value(name, float(a)) for a in args])
    f = _CLOSED_FORMS[name]
    scales = []
    with mp.workdps(30):
        for a, r in zip(args, refs, strict=True):
            a = float(a)
            if a == 0:
                scales.append(abs(r))
                continue
            if name == "expm1c":
                slope = a * mp.diff(f, mp.mpf(a))
            else:  # θ·d/dθ = 2t·d/dt
                slope = 2 * a * mp.diff(lambda u: f(mp.sqrt(u)), mp.mpf(a))
            scales.append(max(abs(r), abs(float(slope))))
    return args, refs, np.array(scales)


@pytest.mark.parametrize("dtype", [np.float64, np.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("name", ALL_NAMES)
def test_values_against_mpmath(name, dtype):
    args, refs, scales = _reference_table(name, np.dtype(dtype).name)
    out = np.asarray(jax.jit(_jfun(name))(jnp.asarray(args, dtype)))
    assert out.dtype == np.dtype(dtype)
    rel = np.abs(out.astype(np.float64) - refs) / scales
    tol = F64_TOL if dtype == np.float64 else F32_TOL
    worst = int(np.argmax(rel))
    assert rel.max() <= tol, (
        f"{name} {np.dtype(dtype).name}: max rel err {rel.max():.3g} at arg={args[worst]!r}"
    )


@pytest.mark.parametrize("name", ALL_NAMES)
def test_switch_point_both_sides(name):
    """float64 values at the last representable arguments on either side of the switch
    agree with the reference (and hence with each other) to 1e-14 relative."""
    fn = _jfun(name)
    for s in _switch_points(name):
        below = np.nextafter(s, -np.inf if s > 0 else np.inf)
        pts = np.array([below, s, np.nextafter(s, np.inf if s > 0 else -np.inf)])
        out = np.asarray(fn(jnp.asarray(pts)))
        refs = np.array([ref_value(name, float(p)) for p in pts])
        floor = abs(float(_exact_coeffs(name)[0])) if "principal" in name else 0.0
        rel = np.abs(out - refs) / np.maximum(np.abs(refs), floor)  # see the Taylor test
        assert rel.max() <= F64_TOL, (name, s, rel)


# ------------------------------------------------------------------------------------
# Taylor coefficients
# ------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", [*_EVEN, "atanc"])
def test_exact_taylor_coefficients(name):
    exact = _exact_coeffs(name)
    used = series._ATAN_COEFFS if name == "atanc" else _FUNCS[name][0].coeffs
    n_used = len(used)
    # the coefficients in use are the exact ones rounded to float64
    assert tuple(float(c) for c in exact[:n_used]) == tuple(used)
    # the exact ones are the Taylor coefficients of the closed form (even powers of θ)
    cs = cauchy_taylor(name, 2 * n_used + 2)
    with mp.workdps(80):
        for k in range(n_used):
            e = mp.mpf(exact[k].numerator) / exact[k].denominator
            # (a coefficient that is exactly zero, β's first, compares absolutely)
            bound = mp.mpf("1e-30") * abs(e) if e != 0 else mp.mpf("1e-60")
            assert abs(cs[2 * k] - e) <= bound, (name, k, cs[2 * k], e)
            assert abs(cs[2 * k + 1]) <= mp.mpf("1e-40"), (name, k, "odd coefficient")
    # the series is truncated where the first dropped term is negligible at t0
    t0 = _FUNCS[name][1]
    dropped = abs(float(exact[n_used])) * t0**n_used
    # (θ/2)cot(θ/2) crosses zero at θ = π: its polynomial form is accurate in absolute terms
    scale = max(abs(ref_value(name, t0)), abs(float(exact[0])) if "principal" in name else 0)
    assert dropped <= 1e-17 * scale, (name, dropped)


def test_cauchy_coefficients_match_mpmath_taylor():
    """The Cauchy-integral coefficients agree with ``mpmath.taylor`` (numerical
    differentiation, which cannot be centred on the removable singularity θ = 0): the
    Taylor polynomial of the closed form at θ = 0.5 equals the re-expansion of the series."""
    with mp.workdps(40):
        for name in ("se3_q_c3", "jinv_coeff", "sinc"):
            f = _CLOSED_FORMS[name]
            x0 = mp.mpf("0.5")
            tay = mp.taylor(f, x0, 4)
            cs = cauchy_taylor(name, 40)
            for m in range(5):  # m-th Taylor coefficient at x0 from the series at 0
                val = mp.fsum(
                    cs[k] * mp.binomial(k, m) * x0 ** (k - m) for k in range(m, len(cs))
                )
                assert abs(val - tay[m]) <= mp.mpf("1e-20") * (1 + abs(tay[m])), (name, m)


# ------------------------------------------------------------------------------------
# derivatives across the switch
# ------------------------------------------------------------------------------------


@functools.cache
def _derivs(name: str):
    """x ↦ [f, df, d²f, d³f] by autodiff, vmapped over x (one compile per dtype)."""
    fn = _jfun(name)
    d1 = jax.grad(fn)
    d2 = jax.grad(d1)
    d3 = jax.grad(d2)

    def one(x):
        return jnp.stack([fn(x), d1(x), d2(x), d3(x)])

    return jax.jit(jax.vmap(one), compiler_options=FAST_COMPILE)


@pytest.mark.parametrize("name", ALL_NAMES)
def test_derivatives_continuous_across_switch(name):
    f = _derivs(name)
    for s in _switch_points(name):
        eps = 1e-9 * abs(s)
        pts = jnp.asarray([s - eps, s + eps])
        out = np.asarray(f(pts))  # (2, 4): value, d1, d2, d3 below / above
        assert np.all(np.isfinite(out))
        for n in (1, 2):
            ref = ref_derivative(name, s, n)
            below, above = out[0, n], out[1, n]
            # the true derivative changes by f^{(n+1)}·2ε ≈ 1e-9 relative over the gap, so
            # compare each side with the reference at its own point
            ref_b = ref_derivative(name, s - eps, n)
            ref_a = ref_derivative(name, s + eps, n)
            assert abs(below - ref_b) <= DERIV_CONT_TOL * abs(ref), (name, s, n, below, ref_b)
            assert abs(above - ref_a) <= DERIV_CONT_TOL * abs(ref), (name, s, n, above, ref_a)
            jump = (above - below) - (ref_a - ref_b)
            assert abs(jump) <= DERIV_CONT_TOL * abs(ref), (name, s, n, "jump", jump)


@pytest.mark.parametrize("name", _EVEN)
def test_derivatives_against_mpmath(name):
    """First to third derivatives in t inside the domain (each function's derivative is
    its own exact derivative series plus the autodiff derivative of the closed form)."""
    f = _derivs(name)
    pts = np.array([1e-3, 0.3, 0.9, 2.0, 5.0, 9.0]) * min(1.0, _T_MAX.get(name, 30.0) / 9.0)
    out = np.asarray(f(jnp.asarray(pts)))
    for i, t in enumerate(pts):
        for n in (1, 2, 3):
            ref = ref_derivative(name, float(t), n)
            scale = max(abs(ref), abs(float(_exact_coeffs(name)[n])) * np.prod(np.arange(1, n + 1)))
            assert abs(out[i, n] - ref) <= 1e-11 * scale, (name, t, n, out[i, n], ref)


@pytest.mark.parametrize("dtype", [np.float64, np.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("name", ALL_NAMES)
def test_derivatives_finite_at_zero_and_switch(name, dtype):
    f = _derivs(name)
    pts = [0.0, *(_switch_points(name))]
    out = np.asarray(f(jnp.asarray(pts, dtype)))
    assert np.all(np.isfinite(out)), (name, out)
    # at 0 the derivatives in t are k!·c_k (θ-series coefficients at even powers)
    if name != "expm1c":
        exact = _exact_coeffs(name)
        want = [float(exact[k]) * float(np.prod(np.arange(1, k + 1))) for k in range(4)]
    else:
        want = [1.0 / (k + 1) for k in range(4)]  # d^k/dx^k (eˣ−1)/x at 0 = k!/(k+1)!
    rtol = 1e-14 if dtype == np.float64 else 1e-6
    np.testing.assert_allclose(out[0], want, rtol=rtol, atol=0, err_msg=name)


# (n², w) on both sides of the derivative's series switch (n² = 0.04·w²), at θ = π (w = 0)
# and for quaternions off the unit sphere
_LOG_POINTS = [(1e-4, 0.99), (0.0399 * 0.25, 0.5), (0.0401 * 0.25, 0.5), (0.3, 0.8),
               (0.9, 0.1), (1.0, 0.0), (0.5, 0.5), (2.0, 3.0)]


def test_quat_log_coeff_derivatives_against_mpmath():
    """The closed-form partial derivatives of 2·atan2(n, w)/n (its ``custom_jvp``), and the
    second derivatives obtained by differentiating them, against mpmath."""

    def ref(n2, w):
        n = mp.sqrt(n2)
        return 2 * mp.atan2(n, w) / n

    grad = jax.jit(jax.grad(series.quat_log_coeff, argnums=(0, 1)))
    hess = jax.jit(jax.hessian(series.quat_log_coeff, argnums=(0, 1)))
    for n2, w in _LOG_POINTS:
        a, b = jnp.float64(n2), jnp.float64(w)
        g = np.array([float(v) for v in grad(a, b)])
        h = np.array([[float(hess(a, b)[i][j]) for j in range(2)] for i in range(2)])
        with mp.workdps(50):
            x, y = mp.mpf(n2), mp.mpf(w)
            g_ref = np.array([float(mp.diff(ref, (x, y), (1, 0))),
                              float(mp.diff(ref, (x, y), (0, 1)))])
            h_ref = np.array([[float(mp.diff(ref, (x, y), (2, 0))),
                               float(mp.diff(ref, (x, y), (1, 1)))],
                              [float(mp.diff(ref, (x, y), (1, 1))),
                               float(mp.diff(ref, (x, y), (0, 2)))]])
        assert np.abs(g - g_ref).max() <= 1e-13 * np.abs(g_ref).max(), (n2, w, g, g_ref)
        assert np.abs(h - h_ref).max() <= 1e-11 * np.abs(h_ref).max(), (n2, w, h, h_ref)
    # at n = 0 the derivative in n² is the series' leading term −2/(3w³)
    np.testing.assert_allclose(float(grad(0.0, 0.5)[0]), -2.0 / (3 * 0.125), rtol=1e-15)


@pytest.mark.parametrize("count", [1, 3])
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_computed_once_is_the_identity_through_a_dot(count, dtype):
    """``computed_once`` returns its arrays bit for bit, with identity derivatives, under
    jit and vmap, and the compiled program keeps the dot that stores them (a single
    array's 1×1 dot used to be simplified into a product, which XLA fuses again)."""
    rng = np.random.default_rng(count)
    arrays = tuple(jnp.asarray(rng.normal(size=(5, 6, 6)), dtype) for _ in range(count))
    fn = jax.jit(series.computed_once)
    for out, a in zip(fn(*arrays), arrays, strict=True):
        assert out.dtype == a.dtype and np.array_equal(np.asarray(out), np.asarray(a))
    batched = jax.jit(jax.vmap(series.computed_once))(*arrays)
    assert all(np.array_equal(np.asarray(o), np.asarray(a)) for o, a in zip(batched, arrays))
    tangents = tuple(jnp.asarray(rng.normal(size=a.shape), dtype) for a in arrays)
    _, t_out = jax.jvp(series.computed_once, arrays, tangents)
    assert all(np.array_equal(np.asarray(o), np.asarray(t)) for o, t in zip(t_out, tangents))
    hlo = fn.lower(*arrays).compile().as_text()
    assert " dot(" in hlo, "computed_once's dot was simplified away"


@pytest.mark.parametrize("dtype", [np.float64, np.float32], ids=["float64", "float32"])
def test_sinc_cos_derivatives_to_sixth_order_against_mpmath(dtype):
    """``sinc_cos``'s derivatives come from one sincos per order (exact series below
    t = 1, the recurrence of sinc's differential equation above): its sixth-order jet and
    six nested ``jax.grad`` of each output equal mpmath's derivatives of sin √t/√t and
    cos √t on both sides of the switch, and are finite at 0."""
    pts = np.array([0.0, 1e-6, 0.3, 0.999, 1.001, 2.5, 9.0, 40.0])
    rtol = 1e-11 if dtype == np.float64 else 2e-4
    jet = np.asarray(jax.jit(lambda t: jnp.stack(series._sinc_cos_jet(t, 6)))(
        jnp.asarray(pts, dtype)))
    fns = [lambda t, i=i: series.sinc_cos(t)[i] for i in (0, 1)]
    nested = []
    for fn in fns:
        ds = [fn]
        for _ in range(6):
            ds.append(jax.grad(ds[-1]))
        nested.append(np.asarray(jax.jit(jax.vmap(lambda t, ds=ds: jnp.stack([d(t) for d in ds])))(
            jnp.asarray(pts, dtype))))
    assert np.all(np.isfinite(jet)) and all(np.all(np.isfinite(n)) for n in nested)
    forms = {0: lambda u: mp.sin(mp.sqrt(u)) / mp.sqrt(u), 1: lambda u: mp.cos(mp.sqrt(u))}
    for i, t in enumerate(pts):
        with mp.workdps(DPS + 30):
            if t == 0.0:  # the k-th derivative in t at 0 is k!·(the k-th series coefficient)
                ref = {j: [float(c) * float(mp.factorial(k)) for k, c in
                           enumerate((series.sinc, series.cos)[j].exact_coeffs[:7])]
                       for j in (0, 1)}
            else:
                ref = {j: [float(mp.diff(forms[j], mp.mpf(float(t)), k)) for k in range(7)]
                       for j in (0, 1)}
        # jet rows: cos, sinc, sinc', …, sinc⁽⁶⁾
        for k in range(7):
            scale = max(abs(ref[0][k]), float(mp.factorial(k)) / float(mp.factorial(2 * k + 1)))
            assert abs(jet[1 + k, i] - ref[0][k]) <= rtol * scale, (t, k, jet[1 + k, i], ref[0][k])
            for j in (0, 1):
                scale_j = max(abs(ref[j][k]), scale)
                assert abs(nested[j][i, k] - ref[j][k]) <= rtol * scale_j, (j, t, k)
        assert abs(jet[0, i] - ref[1][0]) <= rtol * max(abs(ref[1][0]), 1e-3)


def test_computed_once_broadcasts_its_arrays():
    """Arrays of different (broadcastable) shapes come back at the common shape."""
    a, b = series.computed_once(jnp.float32(2.0), jnp.arange(3.0, dtype=jnp.float32))
    assert a.shape == b.shape == (3,)
    np.testing.assert_array_equal(np.asarray(a), [2.0, 2.0, 2.0])
    np.testing.assert_array_equal(np.asarray(b), [0.0, 1.0, 2.0])


def _primitive_names(jaxpr: Any) -> set[str]:
    """Primitive names in ``jaxpr`` and every jaxpr inside it (custom rules, jit, loops)."""
    return {eqn.primitive.name for eqn in equations(jaxpr)}


@pytest.mark.parametrize("axis", [-1, 0])
def test_parts_are_the_components_and_transpose_to_one_concatenate(axis):
    """``parts`` gives ``a``'s components along ``axis``; its transpose is one concatenate,
    not a pad per component (XLA:CPU fuses pads apart, each recomputing the components'
    shared producers) and not the scatter-add of ``jnp.take``."""
    a = jnp.asarray(np.random.default_rng(0).normal(size=(4, 3)))
    cs = parts(a, axis)
    assert len(cs) == a.shape[axis]
    for i, c in enumerate(cs):
        np.testing.assert_array_equal(np.asarray(c), np.take(np.asarray(a), i, axis))

    def f(x):
        return sum(jnp.sum(jnp.sin(c) * k) for k, c in enumerate(parts(x, axis), 1))

    names = _primitive_names(jax.make_jaxpr(jax.grad(f))(a).jaxpr)
    assert "concatenate" in names and not names & {"pad", "gather", "scatter-add"}, names


@pytest.mark.parametrize("fn", ["log", "exp", "jl_inv_apply", "safe_norm_sq", "se3_log",
                                "se3_compose", "se2_log", "se2_exp", "se2_exp_quadratic",
                                "se2_compose", "se2_inv", "se2_act", "se2_jl_inv"])
def test_rotation_derivatives_have_no_pads_or_scatters(fn):
    """First and second derivatives of SO(3)'s Log, Exp, Jl⁻¹·v, |φ|², SE(3)'s Log and
    composition (translation and rotation taken by products, ``_se3._tq_by_products``)
    and SE(2)'s kernels are built from components (``parts``) and stacks, without ``pad``
    (transposed slices), ``gather`` or ``scatter-add`` (transposed ``jnp.take``): those
    made the gradient of a solve over SE(3) residuals compile twice the fused code (and
    the gradient of a solve over intel's SE(2) graph 8 % more)."""
    phi = jnp.asarray(np.random.default_rng(1).normal(size=(5, 3)))
    pose = SE3.exp(jnp.concatenate([phi, phi[::-1]], -1)).data
    pose2 = SE2.exp(phi).data
    f, x = {
        "se2_log": (lambda x: SE2(x).log().data, pose2),
        "se2_exp": (lambda p: SE2.exp(p).data, phi),
        "se2_exp_quadratic": (SE2._exp_quadratic, phi),
        "se2_compose": (lambda x: (SE2(x) @ SE2(x[::-1])).data, pose2),
        "se2_inv": (lambda x: SE2(x).inv().data, pose2),
        "se2_act": (lambda x: SE2(x).act(phi[:, :2]), pose2),
        "se2_jl_inv": (lambda p: SE2._jl_inv(p, principal=True), phi),
        "log": (quat.log, quat.exp(phi)),
        "exp": (quat.exp, phi),
        "jl_inv_apply": (lambda p: quat.jl_inv_apply(p, p[::-1]), phi),
        "safe_norm_sq": (lambda p: series.safe_norm_sq(p)[..., None], phi),
        "se3_log": (lambda x: SE3(x).log().data, pose),
        "se3_compose": (lambda x: (SE3(x) @ SE3(x[::-1])).data, pose),
    }[fn]

    def scalar(y):
        return jnp.sum(jnp.sin(f(y)))

    for g in (jax.grad(scalar), jax.hessian(scalar)):
        names = _primitive_names(jax.make_jaxpr(g)(x).jaxpr)
        assert not names & {"pad", "gather", "scatter-add"}, (fn, names)


def test_series_derivative_rules_store_their_coefficients_once():
    """The jvp rules of the series functions and of the quaternion log's coefficient
    materialise the coefficients every derivative order consumes (one dot each,
    :func:`series.computed_once`): XLA:CPU otherwise copied their polynomials into about a
    dozen fusions of a gradient through a solve."""
    t = jnp.linspace(0.0, 4.0, 7)
    for fn, args in ((series.jinv_coeff, (t,)), (series.quat_log_coeff, (t, 1.0 + t))):
        tangents = tuple(jnp.ones_like(a) for a in args)
        hlo = jax.jit(lambda *a, fn=fn, tangents=tangents: jax.jvp(fn, a, tangents)).lower(
            *args).compile().as_text()
        assert " dot(" in hlo, fn
