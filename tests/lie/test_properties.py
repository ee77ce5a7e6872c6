"""Property-based tests of every Lie group and algebra: SO3, SE3, Sim3, RxSO3, SO2, SE2.

Each property runs over the six groups × float32/float64 (pytest parameters) and hypothesis
draws the batch shape ((), (1,), (3, 1, 2)) and the data. References are independent of the
code under test: matrices built from the documented storage layout, scipy's expm / logm,
hand-built Euler matrices, numpy linear algebra, autodiff and central finite differences.
Computations go through the shared jitted wrappers ``J`` (see conftest: one fast compilation
per op, group, batch shape and dtype for the whole session); eager == jit is checked in
``test_transforms.py``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from jaxpose.lie import SO3, LieAlgebra, LieGroup, convert

from .conftest import (
    BATCH_SHAPES,
    COSSIN_SLICE,
    DATA_SCALE_INDEX,
    DATA_TRANS_SLICE,
    DTYPES,
    GROUPS,
    GROUPS_3D,
    QUAT_SLICE,
    ROT_SLICE,
    J,
    assert_close,
    assert_dtype,
    assert_same_element,
    cases,
    central_diff,
    fast_jit,
    random_group_data,
    random_tangent,
    ref_exp_matrix,
    ref_hat,
    ref_log,
    ref_matrix,
    ref_vee,
    rot_x,
    rot_y,
    rot_z,
)


def _params(groups: tuple[type[LieGroup], ...]) -> list:
    return [
        pytest.param(g, dt, id=f"{g.__name__}-{np.dtype(dt).name}") for g in groups for dt in DTYPES
    ]


group_dtype = pytest.mark.parametrize("cls,dtype", _params(GROUPS))


def _params_f32_slow(groups: tuple[type[LieGroup], ...]) -> list:
    """Like :func:`_params`, but float32 only for SO3/SE3 by default (the others under
    ``-m slow``): for derivative-heavy properties, whose float32 accuracy test_numerics
    also checks against mpmath for every group."""
    return [
        pytest.param(g, dt, id=f"{g.__name__}-{np.dtype(dt).name}",
                     marks=(pytest.mark.slow,)
                     if dt == np.float32 and g.__name__ not in ("SO3", "SE3") else ())
        for g in groups for dt in DTYPES
    ]


group_dtype_heavy = pytest.mark.parametrize("cls,dtype", _params_f32_slow(GROUPS))
group_dtype_3d = pytest.mark.parametrize("cls,dtype", _params(GROUPS_3D))
groups_only = pytest.mark.parametrize("cls", GROUPS, ids=lambda g: g.__name__)


def _eye(cls: type[LieGroup], shape: tuple[int, ...], n: int | None = None) -> np.ndarray:
    n = cls.matrix_dim if n is None else n
    return np.broadcast_to(np.eye(n), (*shape, n, n))


def _check_element(x: LieGroup, cls: type[LieGroup], shape: tuple[int, ...], dtype) -> None:
    assert type(x) is cls, f"expected {cls.__name__}, got {type(x).__name__}"
    assert x.shape == shape and x.data.shape == (*shape, cls.storage_dim)
    assert_dtype(x.data, dtype)


def _check_algebra(a: LieAlgebra, cls: type[LieGroup], shape: tuple[int, ...], dtype) -> None:
    assert type(a) is cls.algebra, f"expected {cls.algebra.__name__}, got {type(a).__name__}"
    assert a.shape == shape and a.data.shape == (*shape, cls.tangent_dim)
    assert_dtype(a.data, dtype)


def _rot_angle(cls: type[LieGroup], data: np.ndarray) -> np.ndarray:
    """Rotation angle in [0, π] of stored elements (numpy)."""
    d = np.asarray(data, np.float64)
    if cls in QUAT_SLICE:
        q = d[..., QUAT_SLICE[cls]]
        return 2 * np.arctan2(np.linalg.norm(q[..., :3], axis=-1), np.abs(q[..., 3]))
    cs = d[..., COSSIN_SLICE[cls]]
    return np.abs(np.arctan2(cs[..., 1], cs[..., 0]))


# ------------------------------------------------------------------------------------
# group axioms, inverse
# ------------------------------------------------------------------------------------
@group_dtype
@given(data=st.data())
def test_group_axioms(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    x, y, z = c.element(), c.element(), c.element()
    mx, my = ref_matrix(cls, x.data), ref_matrix(cls, y.data)

    xy = J.compose(x, y)
    _check_element(xy, cls, c.shape, dtype)
    assert_same_element(xy, mx @ my, dtype, err_msg="closure: X·Y is the matrix product")
    assert_same_element(
        J.compose(xy, z), J.compose(x, J.compose(y, z)), dtype, err_msg="associativity"
    )

    e = cls.identity(c.shape, dtype)
    _check_element(e, cls, c.shape, dtype)
    assert_same_element(e, _eye(cls, c.shape), dtype, f64=0.0, f32=0.0)
    assert_close(J.compose(x, e).data, x.data, dtype, f64=1e-15, f32=1e-7, err_msg="X·I")
    assert_close(J.compose(e, x).data, x.data, dtype, f64=1e-15, f32=1e-7, err_msg="I·X")


@group_dtype
@given(data=st.data())
def test_inverse(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    x = c.element()
    xi = J.inv(x)
    _check_element(xi, cls, c.shape, dtype)
    assert_same_element(xi, np.linalg.inv(ref_matrix(cls, x.data)), dtype)
    eye = _eye(cls, c.shape)
    assert_same_element(J.compose(x, xi), eye, dtype, err_msg="X·X⁻¹ = I")
    assert_same_element(J.compose(xi, x), eye, dtype, err_msg="X⁻¹·X = I")
    assert_close(J.inv(xi).data, x.data, dtype, f64=1e-13, f32=1e-6, err_msg="(X⁻¹)⁻¹ = X")


# ------------------------------------------------------------------------------------
# exp / log
# ------------------------------------------------------------------------------------
@group_dtype
@given(data=st.data())
def test_exp_log_round_trips(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    # Log(Exp(a)) = a for rotation angles below π
    a = c.tangent(max_angle=3.0)
    x = J.exp(c.alg(a))
    _check_element(x, cls, c.shape, dtype)
    assert_same_element(x, ref_exp_matrix(cls, a), dtype, err_msg="Exp(a) = expm(hat(a))")
    la = J.log(x)
    _check_algebra(la, cls, c.shape, dtype)
    assert_close(la.data, a, dtype, err_msg="Log(Exp(a)) = a")

    # Exp(Log(X)) = X for any element (rotation angles up to π), Log = principal logm
    y = c.element()
    ly = J.log(y)
    _check_algebra(ly, cls, c.shape, dtype)
    assert_same_element(J.exp(ly), y, dtype, err_msg="Exp(Log(X)) = X")
    rot = np.asarray(ly.data, np.float64)[..., ROT_SLICE[cls]]
    assert np.all(np.linalg.norm(rot, axis=-1) <= np.pi * (1 + 1e-6)), "log angle exceeds π"
    ok = _rot_angle(cls, y.data) < np.pi - 1e-2  # away from the ±π branch ambiguity
    ref = ref_log(cls, np.asarray(y.data, np.float64))
    assert_close(np.asarray(ly.data)[ok], ref[ok], dtype, f64=1e-9, err_msg="Log vs scipy logm")


_expm = fast_jit(jsl.expm)  # eager expm compiles each of its many primitives separately


@group_dtype
@given(data=st.data())
def test_exp_matrix_is_expm_of_hat(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    a = c.tangent(max_angle=3.0)
    alg = c.alg(a)
    h = J.hat(alg)
    assert_dtype(h, dtype)
    assert_close(h, ref_hat(cls, a), dtype, f64=0.0, f32=0.0, err_msg="hat layout")
    m = J.matrix(J.exp(alg))
    assert_dtype(m, dtype)
    assert_close(m, _expm(h), dtype, f64=1e-12, f32=1e-5, err_msg="Exp(a).matrix()")
    assert_close(m, ref_exp_matrix(cls, a), dtype, f64=1e-12, f32=1e-5)


# ------------------------------------------------------------------------------------
# adjoint
# ------------------------------------------------------------------------------------
@group_dtype
@given(data=st.data())
def test_adjoint_identities(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    x = c.element()
    a, b = c.tangent(max_angle=1.5), c.tangent(max_angle=1.5)
    ad = J.adj(x, c.alg(a))
    _check_algebra(ad, cls, c.shape, dtype)
    # X·Exp(a) = Exp(Adj(X) a)·X
    assert_same_element(
        J.compose(x, J.exp(c.alg(a))), J.compose(J.exp(ad), x), dtype, err_msg="X·Exp(a)"
    )
    # hat(Adj(X) a) = M hat(a) M⁻¹ with the reference matrices
    m = ref_matrix(cls, x.data)
    conj = ref_vee(cls, m @ ref_hat(cls, a) @ np.linalg.inv(m))
    assert_close(ad.data, conj, dtype, err_msg="Adj vs matrix conjugation")
    # <adjT(X) a, b> = <a, Adj(X) b>
    adt = J.adjT(x, c.alg(a))
    _check_algebra(adt, cls, c.shape, dtype)
    lhs = np.sum(np.asarray(adt.data, np.float64) * b, -1)
    rhs = np.sum(a * np.asarray(J.adj(x, c.alg(b)).data, np.float64), -1)
    assert_close(lhs, rhs, dtype, err_msg="<adjT a, b> = <a, Adj b>")
    # adj_matrix is the matrix of the map
    am = np.asarray(J.adj_matrix(x), np.float64)
    assert_close(np.einsum("...ij,...j->...i", am, a), ad.data, dtype)


# ------------------------------------------------------------------------------------
# action on points, matrices
# ------------------------------------------------------------------------------------
@group_dtype
@given(data=st.data())
def test_act_matches_matrix_product(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    x = c.element()
    n = cls.point_dim
    m = ref_matrix(cls, x.data)
    p, ph = c.points(), c.points(homogeneous=True)
    out, out_h = J.act(x, p), J.act(x, ph)
    assert out.shape == p.shape and out_h.shape == ph.shape
    assert_dtype(out, dtype)
    assert_dtype(out_h, dtype)
    p64, ph64 = p.astype(np.float64), ph.astype(np.float64)
    if cls.matrix_dim == n + 1:  # affine groups: [[A, t], [0, 1]]
        expected = np.einsum("...ij,...j->...i", m[..., :n, :n], p64) + m[..., :n, n]
        expected_h = np.einsum("...ij,...j->...i", m, ph64)
    else:  # rotation(-scale) groups act on the first n entries, w passes through
        expected = np.einsum("...ij,...j->...i", m, p64)
        rotated = np.einsum("...ij,...j->...i", m, ph64[..., :n])
        expected_h = np.concatenate([rotated, ph64[..., n:]], -1)
    assert_close(out, expected, dtype, err_msg="act on points")
    assert_close(out_h, expected_h, dtype, err_msg="act on homogeneous points")


@group_dtype
@given(data=st.data())
def test_from_matrix_matrix_round_trip(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    x = c.element()
    m = c.cast(ref_matrix(cls, x.data))
    assert_close(J.matrix(x), m, dtype, f64=1e-14, f32=1e-6, err_msg="matrix() vs layout")
    y = J.from_matrix(jnp.asarray(m), cls, True)
    _check_element(y, cls, c.shape, dtype)
    expected = np.asarray(x.data, np.float64).copy()
    if cls in QUAT_SLICE:  # canonical sign: w ≥ 0
        qs = QUAT_SLICE[cls]
        q = expected[..., qs]
        expected[..., qs] = np.where(q[..., 3:] < 0, -q, q)
        assert np.all(np.asarray(y.data)[..., qs][..., 3] >= 0)
    assert_close(y.data, expected, dtype, err_msg="from_matrix(matrix(X)) storage")
    assert_close(J.matrix(y), m, dtype)


# ------------------------------------------------------------------------------------
# Jacobians
# ------------------------------------------------------------------------------------
@group_dtype_heavy
@given(data=st.data())
def test_jacobian_inverses(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    a = c.tangent(max_angle=3.0)
    alg = c.alg(a)
    jr, jri, jl, jli = J.jr(alg), J.jr_inv(alg), J.jl(alg), J.jl_inv(alg)
    d = cls.tangent_dim
    for mat in (jr, jri, jl, jli):
        assert mat.shape == (*c.shape, d, d)
        assert_dtype(mat, dtype)
    eye = _eye(cls, c.shape, d)
    assert_close(jr @ jri, eye, dtype, err_msg="Jr·Jr⁻¹")
    assert_close(jri @ jr, eye, dtype, err_msg="Jr⁻¹·Jr")
    assert_close(jl @ jli, eye, dtype, err_msg="Jl·Jl⁻¹")
    assert_close(jli @ jl, eye, dtype, err_msg="Jl⁻¹·Jl")
    assert_close(jl, J.jr(c.alg(-a)), dtype, err_msg="Jl(a) = Jr(−a)")


# The batch shapes have 1, 1 and 6 elements: references that work per element take their
# inputs flattened and padded to this many rows, so they compile once per group and dtype
# instead of once per batch shape.
_ROWS = max(int(np.prod(s)) for s in BATCH_SHAPES)


def _padded_rows(x: np.ndarray, width: int) -> jnp.ndarray:
    """``x`` as (−1, width) rows, padded to :data:`_ROWS` rows by repeating the first."""
    flat = np.asarray(x).reshape(-1, width)
    return jnp.asarray(np.concatenate([flat, np.repeat(flat[:1], _ROWS - len(flat), 0)]))


@fast_jit(static_argnums=0)
def _jr_jl_by_autodiff(cls, a):
    """Per-element Jacobians of δ ↦ Log(Exp(a)⁻¹Exp(a+δ)) and δ ↦ Log(Exp(a+δ)Exp(a)⁻¹)."""

    def one(ai):
        zero = jnp.zeros_like(ai)
        right = jax.jacfwd(lambda d: (cls.exp(ai).inv() @ cls.exp(ai + d)).log().data)(zero)
        left = jax.jacrev(lambda d: (cls.exp(ai + d) @ cls.exp(ai).inv()).log().data)(zero)
        return right, left

    return jax.vmap(one)(a)


@group_dtype_heavy
@given(data=st.data())
def test_jr_jl_equal_autodiff_of_exp(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    a = c.tangent(max_angle=3.0)
    d = cls.tangent_dim
    k = int(np.prod(c.shape))
    right, left = (np.asarray(o)[:k] for o in _jr_jl_by_autodiff(cls, _padded_rows(a, d)))
    alg = c.alg(a)
    shape = (*c.shape, d, d)
    assert_close(J.jr(alg), np.reshape(right, shape), dtype, f32=2e-4, err_msg="Jr vs autodiff")
    assert_close(J.jl(alg), np.reshape(left, shape), dtype, f32=2e-4, err_msg="Jl vs autodiff")


@fast_jit(static_argnums=0)
def _dlog_left(cls, x, a):
    """Per row: d/dt Log(Exp(t a)·X) at t = 0, which is Jl⁻¹(Log X)·a (X given as data)."""

    def one(xi, ai):
        return jax.jvp(lambda d: (cls.exp(d) @ cls(xi)).log().data, (jnp.zeros_like(ai),), (ai,))[1]

    return jax.vmap(one)(x, a)


@group_dtype_heavy
@given(data=st.data())
def test_jinvp(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    x = J.exp(c.alg(c.tangent(max_angle=2.5)))
    a = c.tangent(max_angle=1.0)
    out = J.jinvp(x, c.alg(a))
    _check_algebra(out, cls, c.shape, dtype)
    jli = np.asarray(J.jl_inv(J.log(x)), np.float64)
    assert_close(out.data, np.einsum("...ij,...j->...i", jli, a), dtype, err_msg="Jl⁻¹(Log X)·a")
    k = int(np.prod(c.shape))
    dlog = _dlog_left(cls, _padded_rows(x.data, cls.storage_dim), _padded_rows(a, cls.tangent_dim))
    assert_close(out.data, np.reshape(np.asarray(dlog)[:k], a.shape), dtype, f32=2e-4)


def _fd_functions(cls, z, shape):
    """Packed inputs z = [a, b, p] (batch ``shape``) → flattened concatenation of Exp(a),
    Log(Exp(a)·Exp(b)), Exp(a)·p, Adj(Exp(a))·b and Exp(a).matrix()."""
    d, n = cls.tangent_dim, cls.point_dim
    z = z.reshape(*shape, 2 * d + n)
    a, b, p = z[..., :d], z[..., d : 2 * d], z[..., 2 * d :]
    x = cls.exp(a)
    outs = [x.data, (x @ cls.exp(b)).log().data, x @ p, x.adj(b).data, x.matrix()]
    return jnp.concatenate([o.reshape(-1) for o in outs])


@fast_jit(static_argnums=(0, 2))
def _fd_jacobians(cls, z, shape):
    f = functools.partial(_fd_functions, cls, shape=shape)
    return jax.jacfwd(f)(z), jax.jacrev(f)(z)


@fast_jit(static_argnums=(0, 2))
def _fd_batch(cls, zs, shape):
    return jax.vmap(functools.partial(_fd_functions, cls, shape=shape))(zs)


@fast_jit(static_argnums=0)
def _jr_map(cls, a, ds):
    """Log(Exp(a)⁻¹·Exp(a + δ)) for a stack of δ (finite differences of the right Jacobian)."""
    return jax.vmap(lambda d: (cls.exp(a).inv() @ cls.exp(a + d)).log().data)(ds)


@groups_only
@settings(max_examples=4)
@given(data=st.data())
def test_jacobians_fwd_rev_finite_differences(cls, data):
    """jacfwd == jacrev ≈ central finite differences (float64) for exp, log∘compose, act, adj,
    matrix; and Jr ≈ finite differences of Log(Exp(a)⁻¹Exp(a+δ))."""
    # one batch of two elements: its block-diagonal Jacobian holds the unbatched Jacobian of
    # each element (the diagonal blocks) and the independence of the batch elements (the
    # zero blocks). A larger batch only multiplies the size of the Jacobian, and a separate
    # unbatched case only doubles the compilation (tens of seconds per group), without
    # testing anything new.
    c = data.draw(cases(cls, np.float64, shapes=((2,),)))
    d = cls.tangent_dim
    z = np.concatenate(
        [c.tangent(max_angle=1.0), c.tangent(max_angle=1.0), c.points()], -1
    ).reshape(-1)
    jf, jr = _fd_jacobians(cls, jnp.asarray(z), c.shape)
    fd = central_diff(lambda zs: _fd_batch(cls, jnp.asarray(zs), c.shape), z)
    assert_close(jf, jr, np.float64, f64=1e-12, err_msg="jacfwd vs jacrev")
    assert_close(jf, fd, np.float64, f64=1e-7, err_msg="jacfwd vs finite differences")

    a = c.tangent(max_angle=3.0).reshape(-1, d)
    for ai in a:
        fd_jr = central_diff(
            lambda ds, ai=ai: _jr_map(cls, jnp.asarray(ai), jnp.asarray(ds)), np.zeros(d)
        )
        assert_close(J.jr(cls.algebra(ai)), fd_jr, np.float64, f64=1e-7, err_msg="Jr vs FD")


# ------------------------------------------------------------------------------------
# interpolation, cumulative products, normalisation
# ------------------------------------------------------------------------------------
@group_dtype_heavy
@given(data=st.data())
def test_interpolate(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    x = c.element()
    b = c.tangent(max_angle=2.8)
    y = J.compose(x, J.exp(c.alg(b)))
    mx = ref_matrix(cls, x.data)
    assert_same_element(J.interpolate(x, y, 0.0), x, dtype, err_msg="t = 0")
    assert_same_element(J.interpolate(x, y, 1.0), y, dtype, err_msg="t = 1")
    mid = J.interpolate(x, y, 0.5)
    _check_element(mid, cls, c.shape, dtype)
    full = np.linalg.norm(b.astype(np.float64), axis=-1)
    d_first = np.linalg.norm(np.asarray(J.rminus(mid, x), np.float64), axis=-1)
    d_second = np.linalg.norm(np.asarray(J.rminus(y, mid), np.float64), axis=-1)
    assert_close(d_first, 0.5 * full, dtype, err_msg="dist(X, mid) = dist(X, Y)/2")
    assert_close(d_second, 0.5 * full, dtype, err_msg="dist(mid, Y) = dist(X, Y)/2")
    # any t (broadcast over the batch): the geodesic X·Exp(t b)
    t = c.rng.uniform(-0.5, 1.5, size=c.shape)
    zt = J.interpolate(x, y, c.cast(t))
    expected = mx @ ref_exp_matrix(cls, t[..., None] * b.astype(np.float64))
    assert_same_element(zt, expected, dtype, f32=3e-4, err_msg="X·Exp(t Log(X⁻¹Y))")


@group_dtype
@given(data=st.data())
def test_cumprod_matches_loop(cls, dtype, data):
    c = data.draw(cases(cls, dtype, shapes=((1,), (3, 1, 2), (4,))))
    nb = len(c.shape)
    axis = data.draw(st.integers(-nb, nb - 1), label="axis")
    left = data.draw(st.booleans(), label="left")
    x = c.element()
    out = J.cumprod(x, axis, left)
    _check_element(out, cls, c.shape, dtype)
    ms = np.moveaxis(ref_matrix(cls, x.data), axis % nb, 0)
    acc = ms[0]
    expected = [acc]
    for mi in ms[1:]:
        acc = mi @ acc if left else acc @ mi  # left: Yi = Xi·…·X0; right: X0·…·Xi
        expected.append(acc)
    expected = np.moveaxis(np.stack(expected), 0, axis % nb)
    assert_same_element(out, expected, dtype, f32=3e-4, err_msg=f"axis={axis} left={left}")


@group_dtype
@given(data=st.data())
def test_normalize_projects_back(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    x = c.element()
    clean = np.asarray(x.data, np.float64)
    noisy = clean + 1e-2 * c.rng.normal(size=clean.shape)
    y = J.normalize(cls(c.cast(noisy)))
    _check_element(y, cls, c.shape, dtype)
    yd = np.asarray(y.data, np.float64)
    expected = np.asarray(c.cast(noisy), np.float64).copy()  # translation and scale are kept
    rs = QUAT_SLICE.get(cls, COSSIN_SLICE.get(cls))
    expected[..., rs] /= np.linalg.norm(expected[..., rs], axis=-1, keepdims=True)
    assert_close(np.linalg.norm(yd[..., rs], axis=-1), np.ones(c.shape), dtype, f32=1e-6)
    assert_close(yd, expected, dtype, f64=1e-14, f32=1e-6, err_msg="projection")
    if cls in DATA_TRANS_SLICE:
        ts = DATA_TRANS_SLICE[cls]
        assert_close(yd[..., ts], c.cast(noisy)[..., ts], dtype, f64=0.0, f32=0.0)
    if cls in DATA_SCALE_INDEX:
        si = DATA_SCALE_INDEX[cls]
        assert_close(yd[..., si], c.cast(noisy)[..., si], dtype, f64=0.0, f32=0.0)
    assert_same_element(y, x, dtype, f64=0.1, f32=0.1, err_msg="stays near the element")
    assert_close(J.normalize(y).data, yd, dtype, f64=1e-15, f32=1e-7, err_msg="idempotent")
    assert_close(J.normalize(x).data, clean, dtype, f64=1e-15, f32=1e-6, err_msg="no-op on X")


# ------------------------------------------------------------------------------------
# Euler angles, quaternion conventions
# ------------------------------------------------------------------------------------
@group_dtype_3d
@given(data=st.data())
def test_euler_convention_and_round_trip(cls, dtype, data):
    c = data.draw(cases(cls, dtype))
    lim = np.pi - 1e-2
    e = np.stack(
        [
            c.rng.uniform(-lim, lim, size=c.shape),
            c.rng.uniform(-np.pi / 2 + 0.05, np.pi / 2 - 0.05, size=c.shape),
            c.rng.uniform(-lim, lim, size=c.shape),
        ],
        -1,
    )
    r = J.from_euler(c.cast(e))
    _check_element(r, SO3, c.shape, dtype)
    flat = e.reshape(-1, 3)
    hand = np.stack([rot_z(y) @ rot_y(p) @ rot_x(rr) for rr, p, y in flat]).reshape(*c.shape, 3, 3)
    assert_same_element(r, hand, dtype, err_msg="R = Rz(yaw)·Ry(pitch)·Rx(roll)")
    back = J.euler(r)
    assert back.shape == e.shape
    assert_dtype(back, dtype)
    assert_close(back, e, dtype, f32=2e-4, err_msg="euler(from_euler(e)) = e")

    # euler() of any element of the group describes its rotation block
    x = c.element()
    ex = J.euler(x)
    assert ex.shape == (*c.shape, 3)
    assert_dtype(ex, dtype)
    rot = Rotation.from_quat(np.asarray(x.data, np.float64)[..., QUAT_SLICE[cls]].reshape(-1, 4))
    assert_same_element(J.from_euler(ex), rot.as_matrix().reshape(*c.shape, 3, 3), dtype, f32=2e-4)
    pitch = np.asarray(ex, np.float64)[..., 1]
    assert np.all(np.abs(pitch) <= np.pi / 2 + 1e-6)


@fast_jit
def _quaternion_conversions(x, m, rv):
    return (
        x.wxyz(),
        SO3.from_wxyz(x.wxyz()).data,
        convert.xyzw_to_wxyz(x.data),
        convert.wxyz_to_xyzw(convert.xyzw_to_wxyz(x.data)),
        convert.quaternion_to_matrix(x.data),
        convert.matrix_to_quaternion(m),
        convert.rotation_vector_to_matrix(rv),
        convert.matrix_to_rotation_vector(m),
        convert.euler_to_quaternion(rv),
        convert.quaternion_to_euler(x.data),
    )


@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: np.dtype(d).name)
@given(data=st.data())
def test_quaternion_conventions(dtype, data):
    c = data.draw(cases(SO3, dtype))
    x = c.element()
    q = np.asarray(x.data, np.float64)
    rv = c.tangent(max_angle=3.0)
    m = c.cast(Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(*c.shape, 3, 3))
    out = _quaternion_conversions(x, jnp.asarray(m), jnp.asarray(rv))
    for o in out:
        assert_dtype(o, dtype)
    wxyz, back, to_wxyz, to_xyzw, q2m, m2q, rv2m, m2rv, e2q, q2e = out
    exp_wxyz = np.concatenate([q[..., 3:], q[..., :3]], -1)
    assert_close(wxyz, exp_wxyz, dtype, f64=0.0, f32=0.0, err_msg="wxyz order")
    assert_close(to_wxyz, exp_wxyz, dtype, f64=0.0, f32=0.0)
    assert_close(back, q, dtype, f64=0.0, f32=0.0, err_msg="from_wxyz(wxyz())")
    assert_close(to_xyzw, q, dtype, f64=0.0, f32=0.0)
    scipy_wxyz = Rotation.from_quat(q.reshape(-1, 4)).as_quat(scalar_first=True)
    sign = np.sign(scipy_wxyz[:, :1] * exp_wxyz.reshape(-1, 4)[:, :1])
    assert_close(exp_wxyz.reshape(-1, 4), sign * scipy_wxyz, dtype, err_msg="scipy scalar_first")
    assert_close(q2m, m, dtype, err_msg="quaternion_to_matrix")
    canon = np.where(q[..., 3:] < 0, -q, q)
    assert_close(m2q, canon, dtype, err_msg="matrix_to_quaternion (w ≥ 0)")
    flat_rv = rv.astype(np.float64).reshape(-1, 3)
    assert_close(rv2m, Rotation.from_rotvec(flat_rv).as_matrix().reshape(*c.shape, 3, 3), dtype)
    ok = (_rot_angle(SO3, q) < np.pi - 1e-2).reshape(-1)
    ref_rv = Rotation.from_quat(q.reshape(-1, 4)).as_rotvec()
    assert_close(np.asarray(m2rv).reshape(-1, 3)[ok], ref_rv[ok], dtype, f32=2e-4)
    # Euler ↔ quaternion: scipy's extrinsic "xyz" is R = Rz(y)·Ry(p)·Rx(r)
    e2q_ref = Rotation.from_euler("xyz", flat_rv).as_matrix()
    assert_same_element(SO3(e2q), e2q_ref.reshape(*c.shape, 3, 3), dtype)
    q2e_ref = Rotation.from_quat(q.reshape(-1, 4)).as_euler("xyz")
    assert_close(np.asarray(q2e).reshape(-1, 3), q2e_ref, dtype, f32=2e-4)


# ------------------------------------------------------------------------------------
# broadcasting, indexing, reshape, len
# ------------------------------------------------------------------------------------
@fast_jit
def _broadcast_ops(x, y, p, a, t):
    """Every op of the broadcasting test in one compilation (they share no shapes with the
    other tests' wrappers, so separate wrappers would each compile for these shapes alone)."""
    r = x.retract(a)
    return x @ y, x @ p, x.adj(a), r, r.rminus(x), x.interpolate(r, t)


@group_dtype
@given(data=st.data())
def test_broadcasting_between_batch_shapes(cls, dtype, data):
    c = data.draw(cases(cls, dtype, shapes=((3, 1),)))
    x = c.element((3, 1))
    y = c.element((1, 4))
    mx, my = ref_matrix(cls, x.data), ref_matrix(cls, y.data)
    n = cls.point_dim
    p = c.points((1, 4))
    a = c.tangent((1, 4), max_angle=1.0)
    t = c.rng.uniform(0.0, 1.0, size=(1, 4))
    xy, out, ad, r, back, zt = _broadcast_ops(x, y, p, c.alg(a), c.cast(t))

    _check_element(xy, cls, (3, 4), dtype)
    assert_same_element(xy, mx @ my, dtype, err_msg="compose (3,1)·(1,4)")

    assert out.shape == (3, 4, n)
    pts = np.broadcast_to(p.astype(np.float64), (3, 4, n))
    mx_b = np.broadcast_to(mx, (3, 4, *mx.shape[-2:]))
    if cls.matrix_dim == n + 1:
        exp_p = np.einsum("...ij,...j->...i", mx_b[..., :n, :n], pts) + mx_b[..., :n, n]
    else:
        exp_p = np.einsum("...ij,...j->...i", mx_b, pts)
    assert_close(out, exp_p, dtype, err_msg="act (3,1) on points (1,4)")

    _check_algebra(ad, cls, (3, 4), dtype)
    conj = ref_vee(cls, mx @ ref_hat(cls, a) @ np.linalg.inv(mx))
    assert_close(ad.data, conj, dtype, err_msg="adj (3,1) with tangent (1,4)")

    _check_element(r, cls, (3, 4), dtype)
    assert_same_element(r, mx @ ref_exp_matrix(cls, a), dtype, err_msg="retract (3,1)⊕(1,4)")
    assert back.shape == (3, 4, cls.tangent_dim)
    assert_close(back, np.broadcast_to(a, (3, 4, cls.tangent_dim)), dtype)

    _check_element(zt, cls, (3, 4), dtype)
    assert_same_element(zt, mx @ ref_exp_matrix(cls, t[..., None] * a), dtype)


@pytest.mark.parametrize("cls", GROUPS, ids=lambda g: g.__name__)
def test_getitem_reshape_len(cls):
    rng = np.random.default_rng(0)
    data = random_group_data(rng, cls, (3, 1, 2))
    x = cls(data)
    assert x.shape == (3, 1, 2) and len(x) == 3 and x.dtype == np.float64
    for idx, expected in [
        (0, data[0]),
        (-1, data[-1]),
        (slice(1, None), data[1:]),
        ((1, 0), data[1, 0]),
        ((Ellipsis, 1), data[..., 1, :]),
        ((slice(None), 0, slice(None, None, -1)), data[:, 0, ::-1]),
        (np.array([2, 0]), data[np.array([2, 0])]),
    ]:
        y = x[idx]
        assert type(y) is cls
        np.testing.assert_array_equal(np.asarray(y.data), expected, err_msg=str(idx))
    assert x[1, 0, 1].shape == ()
    for shape, args in [((6,), (6,)), ((2, 3), ((2, 3),)), ((2, 3), (2, 3)), ((6,), (-1,))]:
        y = x.reshape(*args)
        assert type(y) is cls and y.shape == shape
        np.testing.assert_array_equal(np.asarray(y.data), data.reshape(*shape, cls.storage_dim))
    assert len(x.reshape(6)) == 6
    with pytest.raises(TypeError):
        len(cls.identity())
    b = x.broadcast_to((4, 3, 1, 2))
    assert b.shape == (4, 3, 1, 2)
    np.testing.assert_array_equal(np.asarray(b.data[2]), data)

    a = random_tangent(rng, cls, (3, 1, 2))
    alg = cls.algebra(a)
    assert alg.shape == (3, 1, 2) and len(alg) == 3
    np.testing.assert_array_equal(np.asarray(alg[1:, 0].data), a[1:, 0])
    np.testing.assert_array_equal(np.asarray(alg[..., 0].data), a[..., 0, :])
    assert alg.reshape(6).shape == (6,)
    with pytest.raises(TypeError):
        len(cls.algebra(np.zeros(cls.tangent_dim)))


@fast_jit(static_argnums=(0, 1))
def _identity_random_components(cls, dtype, key):
    """For every batch shape (one compilation per group and dtype): identity, its matrix,
    random(), its matrix, translation, scale and rotation matrix."""
    out = []
    for shape in BATCH_SHAPES:
        e = cls.identity(shape, dtype)
        x = cls.random(key, shape, sigma=0.5, dtype=dtype)
        out.append(
            (e, e.matrix(), x, x.matrix(), x.translation(), x.scale(), x.rotation().matrix())
        )
    return out


@pytest.mark.parametrize("cls", GROUPS, ids=lambda g: g.__name__)
@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: np.dtype(d).name)
def test_identity_random_components(cls, dtype):
    results = _identity_random_components(cls, dtype, jax.random.key(7))
    for shape, (e, e_m, x, x_m, tr, sc, rot_m) in zip(BATCH_SHAPES, results, strict=True):
        _check_identity_random_components(cls, dtype, shape, e, e_m, x, x_m, tr, sc, rot_m)


def _check_identity_random_components(cls, dtype, shape, e, e_m, x, x_m, tr, sc, rot_m):
    _check_element(e, cls, shape, dtype)
    assert_close(e_m, _eye(cls, shape), dtype, f64=0.0, f32=0.0)
    _check_element(x, cls, shape, dtype)
    m = ref_matrix(cls, x.data)
    assert_close(x_m, m, dtype, err_msg="random() gives a valid element")
    assert not np.allclose(np.asarray(x.data), np.asarray(e.data)), "random() == identity"
    n = cls.point_dim
    assert tr.shape == (*shape, n) and sc.shape == shape
    assert_dtype(tr, dtype)
    assert_dtype(sc, dtype)
    if cls.matrix_dim == n + 1:
        # exact on the CPU; XLA:GPU may compute random()'s data twice in two fusions that
        # round differently (one float32 ulp seen for Sim3 on an H200)
        exact = 0.0 if jax.default_backend() == "cpu" else 2.0**-23
        assert_close(tr, m[..., :n, n], dtype, f64=exact, f32=exact)
        block = m[..., :n, :n]
    else:
        assert_close(tr, np.zeros((*shape, n)), dtype, f64=0.0, f32=0.0)
        block = m
    s = np.abs(np.linalg.det(block)) ** (1.0 / n)
    assert_close(sc, s, dtype, err_msg="scale() = det(block)^(1/n)")
    assert_close(rot_m, block / s[..., None, None], dtype, err_msg="rotation()")
