"""Numerical accuracy and derivative safety of every Lie group against high-precision
references.

Accuracy (``test_*_accuracy``): exp, log, jr, jl, jr_inv and jl_inv of SO3, SE3, Sim3,
RxSO3, SO2 and SE2 over rotation angles θ ∈ [1e-12, π − 1e-9] (log-spaced, dense near π and
straddling every series switch point), random axes, random translations (|ρ| log-uniform in
[0.1, 10]) and log-scales σ (uniform in [−2, 2], tiny, or 0, to cross the e^σ switch). The
error is ‖x − ref‖ / ‖ref‖ (vector / Frobenius norm); exp is compared as a matrix, log as
the algebra vector, each op evaluated under the default ``jax.jit``. Targets: 1e-14
(float64) and 2e-6 (float32). For float32 the reference is evaluated at the float32-rounded
input, so input rounding is not counted.

References come from the definitions, not from the formulas of the code under test:
Exp(a) = expm(hat a); Jl(a) = φ(ad_a) and Jr(a) = φ(−ad_a) with φ(z) = (eᶻ − 1)/z and ad_a
built from commutators of hat matrices (ad_a b = vee([hat a, hat b])); the inverses by
Gauss–Jordan elimination; Log from the stored quaternion (θ = 2·atan2(|v|, |w|)) or
[cos, sin] and the translation by solving W ρ = t with W = φ(A) for the rotation/scale
block A. Scalar transcendental functions are evaluated by mpmath (60 digits); the matrix
series (Taylor with scaling and doubling, no cancellation at small θ) run in exact
fixed-point integer arithmetic with 256 fractional bits, ~20x faster than mpf matrices.

Derivatives (``test_derivatives_*``): values and first derivatives (jacfwd and jacrev) of
exp, log (of stored data, including the quaternion of angle π with w = 0), log∘exp, jr, jl,
jr_inv, jl_inv, act and compose∘log at a = 0, |a| ~ 1e-8, θ = 0 and θ = 1e-8 with
translation / scale, θ = π − 1e-6, θ = π and θ = 0.5, in float32 and float64: finite,
jacfwd == jacrev, equal to closed forms at |a| ≤ 1e-8 (d Log(Exp a)/da = I, Jr(0) = I and
its series, ...) and to float64 Richardson-extrapolated central differences at θ = 0, 1e-8
and 0.5 (with translation). Second and third derivatives (jacrev(jacfwd f) and
jacfwd(jacrev(jacfwd f))) must be finite at the same points. Compiling nested derivatives
dominates the run time, so the default run covers every code path of every group and the
rest of the group × function × dtype grid is marked ``slow``.
"""

from __future__ import annotations

import functools
import math

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import mpmath as mp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from jaxpose.lie import SE2, SE3, SO2, SO3, RxSO3, Sim3  # noqa: E402

from .conftest import FAST_COMPILE  # noqa: E402

GROUPS = (SO3, SE3, Sim3, RxSO3, SO2, SE2)
DTYPES = (np.float64, np.float32)
DPS = 60
TOL = {np.float64: 1e-14, np.float32: 2e-6}
JAC_OPS = ("jr", "jl", "jr_inv", "jl_inv")



def fast_jit(f):
    return jax.jit(f, compiler_options=FAST_COMPILE)


def _gid(x) -> str:
    return getattr(x, "__name__", str(x))


def _params(groups=GROUPS, dtypes=DTYPES):
    return [
        pytest.param(g, dt, id=f"{g.__name__}-{np.dtype(dt).name}") for g in groups for dt in dtypes
    ]


# ====================================================================================
# references: mpmath for the scalar transcendental functions (60 digits) and exact
# fixed-point integer arithmetic with 256 fractional bits (rounding 2^-256 ≈ 1e-77 per
# operation) for the matrix series, which are the expensive part: Python integers on numpy
# object arrays are ~20x faster than mpf and every float input converts exactly.
# ====================================================================================
FRAC = 256
ONE = 1 << FRAC
TINY = 1 << 16  # 2^-240: where the series stops (floor rounding keeps -1 from vanishing)


def fx(x) -> int:
    """float / int / mpf → fixed point (exact for floats)."""
    if isinstance(x, (mp.mpf, mp.mpc)):
        with mp.workdps(DPS + 100):
            return int(mp.nint(mp.re(x) * ONE))
    n, d = float(x).as_integer_ratio()
    return (n << FRAC) // d


def fxa(x) -> np.ndarray:
    """Array of floats or mpf → object array of fixed-point ints."""
    x = np.asarray(x, object if np.asarray(x).dtype == object else np.float64)
    out = np.empty(x.shape, object)
    for idx in np.ndindex(x.shape):
        out[idx] = fx(x[idx])
    return out


def to_float(x: np.ndarray) -> np.ndarray:
    """Fixed-point ints → correctly rounded float64 (int / int is correctly rounded)."""
    return np.vectorize(lambda v: v / ONE, otypes=[np.float64])(x)


def to_mpf(v: int):
    return mp.mpf(v) / ONE


def eye(n: int) -> np.ndarray:
    out = np.zeros((n, n), object)
    for i in range(n):
        out[i, i] = ONE
    return out


def zeros(shape) -> np.ndarray:
    return np.zeros(shape, object)  # python ints


def mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a @ b) >> FRAC


def skew(v) -> np.ndarray:
    x, y, z = v
    return np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]], object)


def expm_phi(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(e^A, φ(A)) with φ(A) = Σ Aᵏ/(k+1)! = ∫₀¹ e^{uA} du, by the Taylor series of A/2ˢ
    (‖A/2ˢ‖ ≤ 1/16) followed by s doublings e^{2B} = (e^B)², φ(2B) = φ(B)(e^B + I)/2."""
    n = a.shape[0]
    ident = eye(n)
    norm = max(sum(abs(int(x)) for x in row) for row in a) / ONE
    s = max(0, math.ceil(math.log2(norm)) + 4) if norm > 0 else 0
    b = a >> s
    e, f, term = ident.copy(), ident.copy(), ident
    k = 1
    while True:
        term = mul(term, b) // k  # Bᵏ/k!
        if max(abs(int(x)) for x in term.flat) <= TINY:
            break
        e = e + term
        f = f + term // (k + 1)
        k += 1
    for _ in range(s):
        f = mul(f, e + ident) >> 1
        e = mul(e, e)
    return e, f


def inverse(m: np.ndarray) -> np.ndarray:
    """Gauss–Jordan with partial pivoting in fixed point."""
    n = m.shape[0]
    a = np.concatenate([m.copy(), eye(n)], 1)
    for c in range(n):
        p = c + int(np.argmax([abs(int(v)) for v in a[c:, c]]))
        a[[c, p]] = a[[p, c]]
        a[c] = (a[c] << FRAC) // a[c, c]
        for r in range(n):
            if r != c and a[r, c]:
                a[r] = a[r] - ((a[r, c] * a[c]) >> FRAC)
    return a[:, n:]


def matvec(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    return (m @ v) >> FRAC


# -- hat / vee in the documented algebra layouts ---------------------------------------
def hat(G, a) -> np.ndarray:
    if G is SO3:
        return skew(a)
    if G is RxSO3:
        return skew(a[:3]) + a[3] * eye(3) // ONE
    if G is SO2:
        return np.array([[0, -a[0]], [a[0], 0]], object)
    if G in (SE3, Sim3):
        m = zeros((4, 4))
        m[:3, :3] = skew(a[3:6]) + (a[6] * eye(3) // ONE if G is Sim3 else 0)
        m[:3, 3] = a[:3]
        return m
    if G is SE2:
        m = zeros((3, 3))
        m[0, 1], m[1, 0] = -a[2], a[2]
        m[:2, 2] = a[:2]
        return m
    raise TypeError(G)


def vee(G, m) -> np.ndarray:
    def so3v(b):
        return np.array([b[2, 1], b[0, 2], b[1, 0]], object)

    if G is SO3:
        return so3v(m)
    if G is RxSO3:
        return np.concatenate([so3v(m), [m[0, 0]]])
    if G is SO2:
        return np.array([m[1, 0]], object)
    if G is SE3:
        return np.concatenate([m[:3, 3], so3v(m)])
    if G is Sim3:
        return np.concatenate([m[:3, 3], so3v(m), [m[0, 0]]])
    if G is SE2:
        return np.array([m[0, 2], m[1, 2], m[1, 0]], object)
    raise TypeError(G)


def ad_matrix(G, a) -> np.ndarray:
    """ad_a with columns vee([hat a, hat e_i])."""
    d = G.tangent_dim
    ha = hat(G, a)
    cols = []
    for i in range(d):
        e = zeros(d)
        e[i] = ONE
        he = hat(G, e)
        cols.append(vee(G, mul(ha, he) - mul(he, ha)))
    return np.stack(cols, 1)


# -- rotation / translation blocks of the stored data ------------------------------------
QUAT = {SO3: slice(0, 4), SE3: slice(3, 7), Sim3: slice(3, 7), RxSO3: slice(0, 4)}
ROT = {SO3: slice(0, 3), SE3: slice(3, 6), Sim3: slice(3, 6), RxSO3: slice(0, 3),
       SO2: slice(0, 1), SE2: slice(2, 3)}
TRANS = {SE3: slice(0, 3), Sim3: slice(0, 3), SE2: slice(0, 2)}
SCALE = {Sim3: 6, RxSO3: 3}


def quat_exp(phi) -> list:
    """[sin(θ/2)/θ·φ, cos(θ/2)] in mpmath (phi: mpf)."""
    th = mp.sqrt(mp.fsum(x * x for x in phi))
    if th == 0:
        return [mp.mpf(0)] * 3 + [mp.mpf(1)]
    return [x * mp.sin(th / 2) / th for x in phi] + [mp.cos(th / 2)]


def quat_log(q) -> list:
    """2·atan2(|v|, |w|)·v/|v| (sign of q chosen so that w ≥ 0), mpmath."""
    v, w = list(q[:3]), q[3]
    if w < 0:
        v, w = [-x for x in v], -w
    n = mp.sqrt(mp.fsum(x * x for x in v))
    if n == 0:
        return [mp.mpf(0)] * 3
    return [x * (2 * mp.atan2(n, w) / n) for x in v]


def rot_block(G, a) -> np.ndarray:
    """The block A of hat(a) that acts on the translation (rotation plus scale)."""
    if G is SE2:
        return hat(SO2, a[2:3])
    return hat(G, a)[:3, :3]


def ref_storage(G, a: np.ndarray) -> np.ndarray:
    """Stored data of Exp(a) as floats (a: float64 tangent), from the layouts."""
    with mp.workdps(DPS):
        am = [mp.mpf(float(v)) for v in a]
        parts = []
        if G in TRANS:
            w = expm_phi(rot_block(G, fxa(a)))[1]
            parts.append(to_float(matvec(w, fxa(a[TRANS[G]]))))
        if G in QUAT:
            parts.append([float(v) for v in quat_exp(am[ROT[G]])])
        else:
            th = am[ROT[G]][0]
            parts.append([float(mp.cos(th)), float(mp.sin(th))])
        if G in SCALE:
            parts.append([float(mp.exp(am[SCALE[G]]))])
    return np.concatenate(parts)


def ref_log(G, x: np.ndarray) -> np.ndarray:
    """Log of stored data x (floats): rotation angle in [0, π], σ = log s, translation from
    W ρ = t with W = φ(A)."""
    with mp.workdps(DPS):
        xm = [mp.mpf(float(v)) for v in x]
        if G in QUAT:
            rot = quat_log(xm[QUAT[G]])
        else:
            cs = xm[2:4] if G is SE2 else xm[0:2]
            rot = [mp.atan2(cs[1], cs[0])]
        out = [mp.mpf(0)] * G.tangent_dim
        out[ROT[G]] = rot
        if G in SCALE:
            out[SCALE[G]] = mp.log(xm[-1])
        out = fxa(np.array(out, object))
    if G in TRANS:
        w = expm_phi(rot_block(G, out))[1]
        out[TRANS[G]] = matvec(inverse(w), fxa(x[: TRANS[G].stop]))
    return to_float(out)


# ====================================================================================
# samples
# ====================================================================================
# θ where a series branch switches: quaternion log (|v|/w = 0.2), t = θ² ∈ {1, 2.25, 4},
# and t = θ²/4 = 1 in the quaternion exponential
SWITCH_THETAS = (2 * math.atan(0.2), 1.0, 1.5, 2.0)


def sample_thetas() -> np.ndarray:
    th = [np.logspace(-12, 0, 24), np.linspace(1.0, np.pi - 1e-3, 10)[1:],
          np.pi - np.logspace(-3, -9, 7)]
    th.append(np.array([s * (1 + d) for s in SWITCH_THETAS for d in (-1e-7, 1e-7)]))
    return np.sort(np.concatenate(th))


def sample_tangents(G, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(θ, tangent vectors) in float64 for group G."""
    rng = np.random.default_rng(seed + GROUPS.index(G))
    th = sample_thetas()
    n = th.size
    a = np.zeros((n, G.tangent_dim))
    if ROT[G].stop - ROT[G].start == 3:
        ax = rng.normal(size=(n, 3))
        a[:, ROT[G]] = ax / np.linalg.norm(ax, axis=1, keepdims=True) * th[:, None]
    else:
        a[:, ROT[G]] = (rng.choice([-1.0, 1.0], n) * th)[:, None]
    if G in TRANS:
        k = TRANS[G].stop - TRANS[G].start
        r = rng.normal(size=(n, k))
        a[:, TRANS[G]] = r / np.linalg.norm(r, axis=1, keepdims=True) * 10 ** rng.uniform(
            -1, 1, (n, 1))
    if G in SCALE:
        sig = rng.uniform(-2, 2, n)
        tiny = rng.choice([-1.0, 1.0], n) * 10 ** rng.uniform(-12, -1, n)
        sig = np.where(np.arange(n) % 3 == 1, tiny, sig)
        sig[::7] = 0.0
        a[:, SCALE[G]] = sig
    return th, a


@functools.cache
def tangent_refs(G, dtype_name: str):
    """Inputs (rounded to dtype) and references for exp and the four Jacobians:
    Exp(a) = e^{hat a}, Jl = φ(ad_a), Jr = φ(−ad_a) = e^{−ad_a} φ(ad_a), and inverses."""
    th, a64 = sample_tangents(G)
    a = a64.astype(dtype_name)
    exps, jacs = [], {k: [] for k in JAC_OPS}
    for row in a:
        af = fxa(row)
        exps.append(to_float(expm_phi(hat(G, af))[0]))
        e, jl = expm_phi(ad_matrix(G, af))
        jr = mul(inverse(e), jl)
        jacs["jl"].append(to_float(jl))
        jacs["jr"].append(to_float(jr))
        jacs["jl_inv"].append(to_float(inverse(jl)))
        jacs["jr_inv"].append(to_float(inverse(jr)))
    return th, a, np.stack(exps), {k: np.stack(v) for k, v in jacs.items()}


@functools.cache
def log_refs(G, dtype_name: str):
    """Stored data of Exp(a) rounded to dtype, and the reference Log of that rounded data."""
    th, a64 = sample_tangents(G, seed=100)
    xs = np.stack([ref_storage(G, row) for row in a64]).astype(dtype_name)
    logs = np.stack([ref_log(G, x) for x in xs])
    return th, xs, logs


def rel_errors(out, ref) -> np.ndarray:
    out = np.asarray(out, np.float64).reshape(len(ref), -1)
    ref = np.asarray(ref, np.float64).reshape(len(ref), -1)
    return np.linalg.norm(out - ref, axis=1) / np.linalg.norm(ref, axis=1)


def _report(name, th, err, tol) -> str:
    i = int(np.argmax(err))
    bad = th[err > tol]
    return (f"{name}: max rel err {err[i]:.3g} at θ={th[i]!r} (tol {tol:g}); "
            f"{bad.size} samples over tol, θ in {bad[:6]}{'...' if bad.size > 6 else ''}")


@functools.cache
def _jitted(G, op: str):
    """The public op under the default ``jax.jit`` (what users run)."""
    if op == "exp":
        return jax.jit(lambda a: G.exp(a).matrix())
    if op == "log":
        return jax.jit(lambda x: G(x).log().data)
    return jax.jit(lambda a: getattr(G.algebra(a), op)())


def _ours(G, op: str, x: np.ndarray) -> np.ndarray:
    return np.asarray(_jitted(G, op)(jnp.asarray(x)))


# ====================================================================================
# 1. accuracy
# ====================================================================================
@pytest.mark.parametrize("G,dtype", _params())
def test_exp_accuracy(G, dtype):
    th, a, exps, _ = tangent_refs(G, np.dtype(dtype).name)
    out = _ours(G, "exp", a)
    assert out.dtype == dtype
    err = rel_errors(out, exps)
    assert err.max() <= TOL[dtype], _report(f"{_gid(G)}.exp", th, err, TOL[dtype])


@pytest.mark.parametrize("G,dtype", _params())
def test_log_accuracy(G, dtype):
    th, x, logs = log_refs(G, np.dtype(dtype).name)
    out = _ours(G, "log", x)
    assert out.dtype == dtype
    err = rel_errors(out, logs)
    assert err.max() <= TOL[dtype], _report(f"{_gid(G)}.log", th, err, TOL[dtype])


@pytest.mark.parametrize("op", JAC_OPS)
@pytest.mark.parametrize("G,dtype", _params())
def test_jacobian_accuracy(G, dtype, op):
    th, a, _, jacs = tangent_refs(G, np.dtype(dtype).name)
    out = _ours(G, op, a)
    assert out.dtype == dtype
    err = rel_errors(out, jacs[op])
    assert err.max() <= TOL[dtype], _report(f"{_gid(G)}.{op}", th, err, TOL[dtype])


@pytest.mark.parametrize("G,dtype", _params(groups=(SO3, SE3, SE2)))
def test_principal_jr_inv_accuracy(G, dtype):
    """``_jl_inv_principal`` (one polynomial per coefficient, valid for angles ≤ π; the
    between factor's analytic Jacobian Jr⁻¹(r) = Jl⁻¹(−r) at r = Log(·)) is as accurate as
    jr_inv on the samples, whose angles run from 0 to π − 1e-9."""
    th, a, _, jacs = tangent_refs(G, np.dtype(dtype).name)
    assert th.max() < np.pi
    out = np.asarray(jax.jit(lambda v: G._jl_inv_principal(-v))(jnp.asarray(a)))
    assert out.dtype == dtype
    err = rel_errors(out, jacs["jr_inv"])
    assert err.max() <= TOL[dtype], _report(f"{_gid(G)}.jr_inv principal", th, err, TOL[dtype])



def _ref_jl_inv_dual(G, a64: np.ndarray, y: np.ndarray) -> np.ndarray:
    """∂(Jl⁻¹(a)ᵀy)/∂a by central differences of the fixed-point reference Jl⁻¹ = φ(ad_a)⁻¹
    with step 2⁻⁶⁰ (error ~2⁻¹²⁰ relative: the arithmetic carries 256 bits)."""
    a, yf, h = fxa(a64), fxa(y), 1 << (FRAC - 60)
    cols = []
    for k in range(G.tangent_dim):
        sides = []
        for sign in (1, -1):
            moved = a.copy()
            moved[k] += sign * h
            jl_inv = inverse(expm_phi(ad_matrix(G, moved))[1])
            sides.append(mul(jl_inv.T, yf.reshape(-1, 1))[:, 0])
        cols.append([((p - m) << FRAC) // (2 * h) for p, m in zip(*sides, strict=True)])
    return to_float(np.asarray(cols, object).T)


@pytest.mark.parametrize("G,dtype", _params(groups=(SE3, SE2)))
def test_principal_jl_inv_dual_closed_form(G, dtype):
    """SE3's and SE2's closed-form ``_jl_inv_principal_dual`` (the exact Hessian of between
    factors uses it) equals central differences of the fixed-point reference over angles
    0 to π − 1e-9, and its own derivative equals the forward-mode derivative of the
    generic rule (jacfwd of ``_jl_inv_principal``) — what third derivatives through
    graph.solve use."""
    from jaxpose.lie._base import LieGroup

    th, a64 = sample_tangents(G)
    pick = np.unique(np.linspace(0, th.size - 1, 12).astype(int))
    y64 = np.random.default_rng(7).normal(size=(pick.size, G.tangent_dim))
    closed = jax.jit(jax.vmap(G._jl_inv_principal_dual))
    jac, jty, dual = closed(jnp.asarray(a64[pick], dtype), jnp.asarray(y64, dtype))
    assert dual.dtype == dtype
    want = np.stack([_ref_jl_inv_dual(G, a, y) for a, y in zip(a64[pick], y64, strict=True)])
    tol = {np.float64: 1e-13, np.float32: 2e-6}[dtype]
    err = rel_errors(dual, want)
    assert err.max() <= tol, _report(f"{_gid(G)} jl_inv dual", th[pick], err, tol)
    np.testing.assert_allclose(jty, np.einsum("nij,ni->nj", np.asarray(jac), y64), rtol=tol,
                               atol=tol)

    def generic(a, y):
        return LieGroup._jl_inv_principal_dual.__func__(G, a, y)[2]

    second = jax.jit(jax.vmap(jax.jacfwd(lambda a, y: G._jl_inv_principal_dual(a, y)[2])))
    second_generic = jax.jit(jax.vmap(jax.jacfwd(generic)))
    args = (jnp.asarray(a64[pick], dtype), jnp.asarray(y64, dtype))
    np.testing.assert_allclose(second(*args), second_generic(*args), rtol=10 * tol,
                               atol=10 * tol * float(np.abs(second_generic(*args)).max()))

def test_references_are_consistent():
    """Self-check of the reference machinery: Log(Exp(a)) = a for every group, Jr = Jlᵀ on
    SO3, and Exp(a + δ) = Exp(a)·Exp(Jr δ) + O(δ²) on Sim3 (δ ~ 1e-20)."""
    for G in GROUPS:
        _, a = sample_tangents(G)
        for row in a[[5, 30, 45]]:
            back = ref_log(G, ref_storage(G, row))
            # the stored data is rounded to float64, so agreement is at float64 level
            np.testing.assert_allclose(back, row, rtol=1e-15, atol=1e-300, err_msg=_gid(G))
    row = fxa(sample_tangents(SO3)[1][20])
    e, jl = expm_phi(ad_matrix(SO3, row))
    jr = mul(inverse(e), jl)
    assert max(abs(int(x)) for x in (jr - jl.T).flat) < ONE >> 200
    row = fxa(sample_tangents(Sim3)[1][40])
    e, jl = expm_phi(ad_matrix(Sim3, row))
    jr = mul(inverse(e), jl)
    delta = np.array([fx(v * 1e-20) for v in np.linspace(-1, 1, 7)], object)
    lhs = expm_phi(hat(Sim3, row + delta))[0]
    rhs = mul(expm_phi(hat(Sim3, row))[0], expm_phi(hat(Sim3, matvec(jr, delta)))[0])
    assert max(abs(int(x)) for x in (lhs - rhs).flat) < fx(1e-36)
    # and the O(δ) term is really there: Exp(a)·Exp(δ) differs at 1e-20
    rhs0 = mul(expm_phi(hat(Sim3, row))[0], expm_phi(hat(Sim3, delta))[0])
    assert max(abs(int(x)) for x in (lhs - rhs0).flat) > fx(1e-22)


# ====================================================================================
# 2. derivatives at the singular points
# ====================================================================================
POINT_NAMES = ("zero", "tiny", "theta0", "theta1e-8", "pi-1e-6", "pi", "theta0.5")
SMALL_POINTS = (0, 1)  # |a| ≤ 1e-8: the closed-form first derivatives hold
FD_POINTS = (2, 3, 6)  # float64 finite differences


def derivative_points(G, dtype) -> tuple[np.ndarray, np.ndarray]:
    """Tangent vectors and stored data at the test points, built without the code under
    test. "zero": a = 0; "tiny": every component of a of size ~1e-8; the others have the
    named rotation angle plus a translation ~N(0, 1) and σ = 0.3 where the group has them.
    The stored data at θ = π has w = 0 (quaternion) or [cos, sin] = [−1, 0] exactly."""
    rng = np.random.default_rng(7)
    ax = rng.normal(size=3)
    ax /= np.linalg.norm(ax)
    rho = rng.normal(size=3)
    thetas = (0.0, None, 0.0, 1e-8, np.pi - 1e-6, np.pi, 0.5)
    a = np.zeros((len(thetas), G.tangent_dim))
    x = []
    for i, th in enumerate(thetas):
        if th is None:  # "tiny"
            u = rng.normal(size=G.tangent_dim)
            a[i] = 1e-8 * u / np.linalg.norm(u)
        else:
            if ROT[G].stop - ROT[G].start == 3:
                a[i, ROT[G]] = ax * th
            else:
                a[i, ROT[G]] = th
            if i > 0 and G in TRANS:
                a[i, TRANS[G]] = rho[: TRANS[G].stop - TRANS[G].start]
            if i > 0 and G in SCALE:
                a[i, SCALE[G]] = 0.3
        rot = a[i, ROT[G]]
        angle = float(np.linalg.norm(rot))
        parts = []
        if G in TRANS:
            parts.append(a[i, TRANS[G]])  # any translation will do for the stored data
        if G in QUAT:
            axis = rot / angle if angle > 0 else ax
            w = 0.0 if th == np.pi else np.cos(angle / 2)
            s = 1.0 if th == np.pi else np.sin(angle / 2)
            parts.append(np.concatenate([axis * s, [w]]))
        else:
            r = float(rot[0])
            parts.append([-1.0, 0.0] if th == np.pi else [np.cos(r), np.sin(r)])
        if G in SCALE:
            parts.append([np.exp(a[i, SCALE[G]])])
        x.append(np.concatenate(parts))
    return a.astype(dtype), np.asarray(x, dtype)


FUNCS = ("exp", "log", "log_exp", "jr", "jl", "jr_inv", "jl_inv", "act", "compose_log")


def make_fn(G, name: str):
    """(f, uses_data): f maps one input vector to an output array. ``log`` takes stored data;
    ``compose_log`` takes (data, δ) and is differentiated in δ at δ = 0."""
    alg = G.algebra
    p = jnp.asarray(np.linspace(0.3, 0.9, G.point_dim))
    if name == "exp":
        return lambda a: G.exp(a).matrix()
    if name == "log":
        return lambda x: G(x).log().data
    if name == "log_exp":
        return lambda a: G.exp(a).log().data
    if name in JAC_OPS:
        return lambda a: getattr(alg(a), name)()
    if name == "act":
        return lambda a: G.exp(a).act(p.astype(a.dtype))
    if name == "compose_log":
        return lambda x, d: (G(x) @ G.exp(d)).log().data
    raise ValueError(name)


def _first_order(G, name):
    f = make_fn(G, name)
    if name == "compose_log":
        def one(x):
            g = functools.partial(f, x)
            d0 = jnp.zeros(G.tangent_dim, x.dtype)
            return g(d0), jax.jacfwd(g)(d0), jax.jacrev(g)(d0)
    else:
        def one(v):
            return f(v), jax.jacfwd(f)(v), jax.jacrev(f)(v)
    return fast_jit(jax.vmap(one))


@functools.cache
def first_order(G, name):
    return _first_order(G, name)


@functools.cache
def values(G, name):
    """f vmapped over inputs (for finite differences)."""
    return fast_jit(jax.vmap(make_fn(G, name)))


@functools.cache
def higher_order(G, name):
    """Per point: the full second derivative jacrev(jacfwd f) and the third derivative
    jacfwd(jacrev(jacfwd g)) of g = Σ w·f with fixed random weights w (a NaN or inf in
    any third derivative of f propagates into g's; the full third derivative of a 7×7
    matrix output needs tens of GiB under vmap)."""
    f = make_fn(G, name)
    if name == "compose_log":
        def one(x):
            g = functools.partial(f, x)
            d0 = jnp.zeros(G.tangent_dim, x.dtype)
            return _second_and_contracted_third(g, d0)
    else:
        def one(v):
            return _second_and_contracted_third(f, v)
    return jax.jit(jax.vmap(one), compiler_options=THIRD_DERIVATIVE_COMPILE)


# jaxlib 0.10.2's XLA:CPU segfaults while running the third derivative of Sim(3)'s `jr`
# in float32 (in a YNNPACK fusion's transpose, slinky::can_fuse; the same program runs
# with YNN fusions off, and crashed an xdist worker of every all-tiers run): these
# programs are compiled without them (a CPU option: FAST_COMPILE is empty on other
# backends, which get none). Production code keeps XLA's defaults.
THIRD_DERIVATIVE_COMPILE = ({**FAST_COMPILE, "xla_cpu_experimental_ynn_fusion_type": ""}
                            if FAST_COMPILE else {})


def _second_and_contracted_third(f, v):
    h2 = jax.jacrev(jax.jacfwd(f))(v)
    w = jax.random.normal(jax.random.key(0), jax.eval_shape(f, v).shape, h2.dtype)
    g = lambda u: jnp.vdot(w, f(u))  # noqa: E731 - Σ w·f: its derivatives are Σ w·(f's)
    return h2, jax.jacfwd(jax.jacrev(jax.jacfwd(g)))(v)


def _input(G, name, dtype):
    a, x = derivative_points(G, dtype)
    return x if name in ("log", "compose_log") else a


def _ad64(G, a) -> np.ndarray:
    return to_float(ad_matrix(G, fxa(a)))


def _hat64(G, a) -> np.ndarray:
    return to_float(hat(G, fxa(a)))


def expected_first_derivative(G, name, a) -> np.ndarray | None:
    """Closed-form first derivative at small a (to O(|a|²) ≤ 1e-16), from hat / ad only.

    Jl = I + ad/2 + ad²/6 + …, Jr = I − ad/2 + ad²/6, Jl⁻¹ = I − ad/2 + ad²/12,
    Jr⁻¹ = I + ad/2 + ad²/12, d Exp(a)/da_i = E_i + (A E_i + E_i A)/2 (A = hat a, E_i =
    hat e_i), d Log(Exp(a))/da = I, d Log(Exp(a)·Exp(δ))/dδ = Jr⁻¹(a)."""
    d = G.tangent_dim
    basis = np.eye(d)
    if name == "log_exp":
        return np.eye(d)
    if name == "compose_log":
        ad = _ad64(G, a)
        return np.eye(d) + ad / 2 + ad @ ad / 12
    if name == "exp":
        A = _hat64(G, a)
        cols = []
        for i in range(d):
            E = _hat64(G, basis[i])
            cols.append(E + (A @ E + E @ A) / 2)
        return np.stack(cols, -1)
    if name == "act":
        A = _hat64(G, a)
        n = G.point_dim
        p = np.linspace(0.3, 0.9, n)
        ph = np.concatenate([p, [1.0]]) if A.shape[0] == n + 1 else p
        cols = []
        for i in range(d):
            E = _hat64(G, basis[i])
            cols.append(((E + (A @ E + E @ A) / 2) @ ph)[:n])
        return np.stack(cols, -1)
    if name in JAC_OPS:
        ad = _ad64(G, a)
        sign = {"jl": 1, "jr": -1, "jl_inv": -1, "jr_inv": 1}[name]
        c2 = 6.0 if name in ("jl", "jr") else 12.0
        cols = []
        for i in range(d):
            adi = _ad64(G, basis[i])
            cols.append(sign * adi / 2 + (adi @ ad + ad @ adi) / c2)
        return np.stack(cols, -1)
    return None  # ``log`` of stored data: checked against finite differences only


def richardson_points(v: np.ndarray, h: float = 1e-3) -> np.ndarray:
    """The (4n, n) evaluation points of :func:`richardson_fd`: v ± (h/2)·eᵢ, then v ± h·eᵢ."""
    E = np.eye(v.size)
    return np.concatenate([v[None] + s * E for s in (h / 2, -h / 2, h, -h)])


def richardson_from(out: np.ndarray, h: float = 1e-3) -> np.ndarray:
    """Central differences with one Richardson step (error O(h⁴)) from f evaluated at
    :func:`richardson_points`, float64, (..., n)."""
    out = np.asarray(out, np.float64)
    n = len(out) // 4

    def cd(plus, minus, step):
        return np.moveaxis((plus - minus) / (2 * step), 0, -1)

    return (4 * cd(out[:n], out[n : 2 * n], h / 2) - cd(out[2 * n : 3 * n], out[3 * n :], h)) / 3


def richardson_fd(f, v: np.ndarray, h: float = 1e-3) -> np.ndarray:
    """Central differences with one Richardson step (error O(h⁴)), float64, (..., n)."""
    return richardson_from(f(jnp.asarray(richardson_points(v, h))), h)


# Compiling nested derivatives dominates the run time (about 1-3 CPU-seconds per function
# for first derivatives and 5-20 for third derivatives on this machine), so the default run
# covers, in both dtypes, every code path of every group: the SO3 exponential, logarithm and
# Jacobian series in quaternion.py (shared by SE3, Sim3 and RxSO3), SE3's V / Q blocks,
# Sim3's quadrature, expm1c and linear solves, RxSO3's scale, SO2's atan2 at (−1, 0) and
# SE2's V and V⁻¹. jl and jl_inv are jr and jr_inv at −a (the same code). The remaining
# combinations of the grid are marked slow (run them with ``-m slow``).
FIRST_DEFAULT = {
    SO3: ("exp", "log", "log_exp", "jr", "jr_inv", "act", "compose_log"),
    SE3: ("exp", "log", "jr", "jr_inv"),
    Sim3: ("exp", "log", "jr", "jr_inv"),
    RxSO3: ("exp", "log"),
    SO2: FUNCS,
    SE2: ("exp", "log", "jr", "jr_inv"),
}
HIGHER_DEFAULT = {
    SO3: ("log", "jr_inv"),
    SE3: (),
    Sim3: (),
    RxSO3: (),
    SO2: FUNCS,
    SE2: ("log",),
}


def _grid(default):
    out = []
    for G in GROUPS:
        for dt in DTYPES:
            for name in FUNCS:
                marks = () if name in default[G] else (pytest.mark.slow,)
                out.append(pytest.param(G, dt, name, marks=marks,
                                        id=f"{G.__name__}-{np.dtype(dt).name}-{name}"))
    return out


@pytest.mark.parametrize("G,dtype,name", _grid(FIRST_DEFAULT))
def test_derivatives_first_order(G, dtype, name):
    """Values, jacfwd and jacrev: finite at every point, fwd == rev, and correct."""
    v = _input(G, name, dtype)
    # float64: the finite-difference points ride along in the same vmapped call (their
    # values are f's; evaluating them separately would compile f once more)
    fd_along = dtype == np.float64 and name != "compose_log"
    pts = [richardson_points(v[i]) for i in FD_POINTS] if fd_along else []
    out = first_order(G, name)(jnp.asarray(np.concatenate([v, *pts])))
    val, jf, jr = (np.asarray(o)[: len(v)] for o in out)
    for label, arr in (("value", val), ("jacfwd", jf), ("jacrev", jr)):
        bad = [POINT_NAMES[i] for i in range(len(v)) if not np.all(np.isfinite(arr[i]))]
        assert not bad, f"{_gid(G)} {name} {label} non-finite at {bad}"
    t = 1e-12 if dtype == np.float64 else 2e-5
    scale = 1 + np.max(np.abs(jf), axis=tuple(range(1, jf.ndim)))
    for i in range(len(v)):
        assert np.max(np.abs(jf[i] - jr[i])) <= t * scale[i], (name, POINT_NAMES[i], "fwd/rev")
    a, _ = derivative_points(G, np.float64)
    for i in SMALL_POINTS:
        want = expected_first_derivative(G, name, a[i])
        if want is None:
            continue
        np.testing.assert_allclose(jf[i], want, rtol=0, atol=10 * t,
                                   err_msg=f"{_gid(G)} {name} at {POINT_NAMES[i]}")
    if name == "log_exp":  # d Log(Exp(a))/da = I wherever Log inverts Exp (θ < π)
        for i in range(len(v)):
            if POINT_NAMES[i] != "pi":
                np.testing.assert_allclose(jf[i], np.eye(G.tangent_dim), rtol=0,
                                           atol=1e3 * t, err_msg=POINT_NAMES[i])
    if dtype == np.float64:
        fd_values = np.split(np.asarray(out[0])[len(v) :], len(pts)) if fd_along else []
        for k, i in enumerate(FD_POINTS):
            if name == "compose_log":
                f, x = values(G, name), jnp.asarray(v[i])
                fd = richardson_fd(lambda d, x=x: f(jnp.broadcast_to(x, (len(d), x.size)), d),
                                   np.zeros(G.tangent_dim))
            else:
                fd = richardson_from(fd_values[k])
            np.testing.assert_allclose(
                jf[i], fd, rtol=0, atol=1e-9 * (1 + np.abs(fd).max()),
                err_msg=f"{_gid(G)} {name} at {POINT_NAMES[i]} vs finite differences")


@pytest.mark.parametrize("G,dtype,name", _grid(HIGHER_DEFAULT))
def test_derivatives_higher_order_finite(G, dtype, name):
    """jacrev(jacfwd f) and (contracted) jacfwd(jacrev(jacfwd f)) are finite at every point."""
    v = _input(G, name, dtype)
    h2, h3 = (np.asarray(o) for o in higher_order(G, name)(jnp.asarray(v)))
    for label, arr in (("second", h2), ("third", h3)):
        bad = [POINT_NAMES[i] for i in range(len(v)) if not np.all(np.isfinite(arr[i]))]
        assert not bad, f"{_gid(G)} {name} {label} derivative non-finite at {bad}"


@pytest.mark.parametrize("shape", [(5, 6, 6, 6), (3, 2, 12, 12), (2, 4, 20, 3), (1, 1, 1)])
def test_small_matmul_equals_matmul_and_differentiates(shape):
    """The fused outer-product form (inner sizes ≤ 16) and the matmul fallback (> 16)
    against numpy's matmul, with the product rule for the derivative."""
    from jaxpose.lie._base import small_matmul

    *batch, n, k, p = shape
    rng = np.random.default_rng(1)
    a = rng.normal(size=(*batch, n, k))
    b = rng.normal(size=(*batch, k, p))
    np.testing.assert_allclose(jax.jit(small_matmul)(a, b), a @ b, rtol=1e-13, atol=1e-13)
    da, db = rng.normal(size=a.shape), rng.normal(size=b.shape)
    _, tangent = jax.jvp(small_matmul, (jnp.asarray(a), jnp.asarray(b)),
                         (jnp.asarray(da), jnp.asarray(db)))
    np.testing.assert_allclose(tangent, da @ b + a @ db, rtol=1e-12, atol=1e-12)
    a32 = jnp.asarray(a, jnp.float32)
    out32 = small_matmul(a32, jnp.asarray(b, jnp.float32))
    assert out32.dtype == jnp.float32
    np.testing.assert_allclose(out32, a @ b, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize(
    "group",
    [SO3] + [pytest.param(g, marks=pytest.mark.slow) for g in (SO2, SE2, SE3, RxSO3, Sim3)],
    ids=lambda g: g.__name__,
)
def test_retract_linear_gives_exact_jacobians_and_their_derivatives(group):
    """``retract_linear`` (``retract_quadratic``) matches ``retract`` in value and first
    (and second) derivative at δ = 0, so Jacobians (Hessians) at δ = 0 agree, and so do
    their derivatives with respect to X (the storage) and to the other argument; the
    closed-form E(δ) (E₂(δ)) is the Taylor polynomial of Exp."""
    kx, ky = jax.random.split(jax.random.PRNGKey(3))
    x, y = group.random(kx, (), sigma=0.7), group.random(ky, (), sigma=0.7)
    zero = jnp.zeros(group.tangent_dim)

    # each derivative is one compiled program (run op by op, the third-order ones took ~20 s)
    def jac(retract):
        def f(xdata, ydata):
            r = lambda d: getattr(group(xdata), retract)(d).rminus(group(ydata))
            return jax.jacfwd(r)(zero)
        return f

    exact = fast_jit(jac("retract"))(x.data, y.data)
    np.testing.assert_allclose(fast_jit(jac("retract_linear"))(x.data, y.data), exact,
                               atol=1e-13)
    for arg in (0, 1):  # derivatives of the Jacobian with respect to X and to Y
        d_exact = fast_jit(jax.jacfwd(jac("retract"), argnums=arg))(x.data, y.data)
        d_linear = fast_jit(jax.jacfwd(jac("retract_linear"), argnums=arg))(x.data, y.data)
        np.testing.assert_allclose(d_linear, d_exact, atol=1e-12)
    np.testing.assert_allclose(group._exp_linear(zero), group._exp(zero), atol=0)
    np.testing.assert_allclose(jax.jacfwd(group._exp_linear)(zero),
                               jax.jacfwd(group._exp)(zero), atol=1e-15)
    # retract_quadratic: the same one order higher (exact Hessians in the tangent chart)
    np.testing.assert_allclose(jax.hessian(group._exp_quadratic)(zero),
                               jax.hessian(group._exp)(zero), atol=1e-15)

    def hess(retract):
        def f(xdata, ydata):
            r = lambda d: jnp.sum(getattr(group(xdata), retract)(d).rminus(group(ydata)) ** 2)
            return jax.hessian(r)(zero)
        return f

    exact = fast_jit(hess("retract"))(x.data, y.data)
    np.testing.assert_allclose(fast_jit(hess("retract_quadratic"))(x.data, y.data), exact,
                               atol=1e-12)
    d_exact = fast_jit(jax.jacfwd(hess("retract")))(x.data, y.data)
    d_quad = fast_jit(jax.jacfwd(hess("retract_quadratic")))(x.data, y.data)
    np.testing.assert_allclose(d_quad, d_exact, atol=1e-11)


@pytest.mark.parametrize("dtype, sigmas", [(jnp.float32, [34.0, 50.0, 80.0]),
                                           (jnp.float64, [250.0, 400.0, 700.0])])
def test_sim3_log_at_large_scale(dtype, sigmas):
    """W·ρ = t was solved by a 3×3 adjugate over a determinant growing as (e^σ/σ)³: past
    σ ≈ 34 (float32) / 250 (float64) the determinant overflowed and log returned ρ = 0,
    then NaN, though t and s = e^σ are finite. The exact answer is the ρ exp was given."""
    xi = jnp.asarray([[1.0, 2.0, 3.0, 0.1, 0.2, 0.3, sigma] for sigma in sigmas], dtype)
    x = Sim3.exp(xi)
    assert np.all(np.isfinite(np.asarray(x.data)))
    out = np.asarray(x.log().data)
    np.testing.assert_allclose(out, np.asarray(xi), rtol=2e-6 if dtype == jnp.float32
                               else 1e-12)
