"""Bad input to the Lie groups gives a clear exception naming what was expected.

Shapes and types are checked at trace time (ValueError / TypeError that name the class, the
argument or the operation and the expected layout); values that are only known at run time
(``from_matrix(check=True)``) raise through ``eqx.error_if``, eagerly and under ``jax.jit``.
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose as jp
from jaxpose.lie import SE2, SE3, SO2, SO3, se3, so3

from .conftest import (
    ALGEBRAS,
    DATA_SCALE_INDEX,
    GROUPS,
    QUAT_SLICE,
    fast_jit,
    random_group_data,
)

by_group = pytest.mark.parametrize("cls", GROUPS, ids=lambda g: g.__name__)
by_algebra = pytest.mark.parametrize("alg", ALGEBRAS, ids=lambda a: a.__name__)


def _other_group(cls):
    return SE3 if cls is not SE3 else SO3


def _element(cls, shape=()):
    return cls(random_group_data(np.random.default_rng(0), cls, shape))


# ------------------------------------------------------------------------------------
# wrong last dimension
# ------------------------------------------------------------------------------------
@by_group
@pytest.mark.parametrize("delta", [-1, 1])
def test_group_wrong_storage_dim(cls, delta):
    bad = np.zeros((2, cls.storage_dim + delta))
    with pytest.raises(ValueError) as err:
        cls(bad)
    msg = str(err.value)
    assert cls.__name__ in msg
    assert f"(..., {cls.storage_dim})" in msg
    assert cls.layout in msg, f"message does not state the layout {cls.layout}: {msg}"
    assert str(bad.shape) in msg


@by_group
def test_group_scalar_data(cls):
    with pytest.raises(ValueError, match=re.escape(cls.layout)):
        cls(1.0)


@by_algebra
@pytest.mark.parametrize("delta", [-1, 1])
def test_algebra_wrong_tangent_dim(alg, delta):
    d = alg.tangent_dim
    if d + delta == 0:
        bad = np.zeros((2, 0))
    else:
        bad = np.zeros((2, d + delta))
    with pytest.raises(ValueError) as err:
        alg(bad)
    msg = str(err.value)
    assert alg.__name__ in msg and f"(..., {d})" in msg and alg.layout in msg


@by_group
def test_wrong_dims_in_operations(cls):
    x = _element(cls, (2,))
    d, n = cls.tangent_dim, cls.point_dim
    with pytest.raises(ValueError, match=rf"{cls.__name__}\.exp.*\(\.\.\., {d}\)"):
        cls.exp(np.zeros((2, d + 1)))
    with pytest.raises(ValueError, match=rf"act\(points\).*\(\.\.\., {n} or {n + 1}\)"):
        x.act(np.zeros((2, n + 2)))
    with pytest.raises(ValueError, match=r"act\(points\)"):
        x @ np.zeros((2, n - 1))
    for method in ("adj", "adjT", "jinvp", "retract"):
        with pytest.raises(
            ValueError, match=rf"{cls.__name__}\.{method}.*{re.escape(cls.algebra.layout)}"
        ):
            getattr(x, method)(np.zeros((2, d + 1)))
    m = cls.matrix_dim
    with pytest.raises(ValueError, match=rf"from_matrix.*\(\.\.\., {m}, {m}\)"):
        cls.from_matrix(np.eye(m + 1))
    with pytest.raises(ValueError, match=rf"from_matrix.*\(\.\.\., {m}, {m}\)"):
        cls.from_matrix(np.zeros(m))


def test_conversion_wrong_dims():
    with pytest.raises(ValueError, match=r"from_euler.*\[roll, pitch, yaw\]"):
        SO3.from_euler(np.zeros(4))
    with pytest.raises(ValueError, match=r"from_euler"):
        jp.from_euler(np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"from_wxyz.*\[qw, qx, qy, qz\]"):
        SO3.from_wxyz(np.zeros(3))


# ------------------------------------------------------------------------------------
# wrong group types
# ------------------------------------------------------------------------------------
@by_group
def test_compose_wrong_group_type(cls):
    other = _other_group(cls)
    x, y = _element(cls), _element(other)
    for call in (lambda: x @ y, lambda: x.compose(y), lambda: jp.compose(x, y)):
        with pytest.raises(TypeError) as err:
            call()
        msg = str(err.value)
        assert cls.__name__ in msg and other.__name__ in msg, msg
    with pytest.raises(TypeError, match=rf"{cls.__name__}.*{other.__name__}"):
        x.interpolate(y, 0.5)
    with pytest.raises(TypeError, match=rf"{cls.__name__}.*{other.__name__}"):
        x.rminus(y)


@by_algebra
def test_algebra_arithmetic_wrong_type(alg):
    other = se3 if alg is not se3 else so3
    a = alg(np.zeros(alg.tangent_dim))
    b = other(np.zeros(other.tangent_dim))
    with pytest.raises(TypeError, match=rf"{alg.__name__}.*{other.__name__}"):
        a + b
    with pytest.raises(TypeError, match=rf"{alg.__name__}.*{other.__name__}"):
        a - b


@by_group
def test_algebra_where_group_expected(cls):
    a = cls.algebra(np.zeros(cls.tangent_dim))
    x = _element(cls)
    with pytest.raises(TypeError, match=rf"{cls.__name__} @ {cls.algebra.__name__}"):
        x @ a
    with pytest.raises(TypeError, match=rf"{cls.__name__}.*{cls.algebra.__name__}"):
        x.compose(a)
    for fn in (jp.log, jp.inv, jp.normalize, jp.translation, jp.scale):
        with pytest.raises(
            TypeError, match=rf"expected a Lie group element, got {cls.algebra.__name__}"
        ):
            fn(a)
    with pytest.raises(TypeError, match="expected a Lie group element"):
        jp.compose(a, x)
    with pytest.raises(TypeError, match="expected a Lie group element"):
        jp.act(a, np.zeros(cls.point_dim))
    with pytest.raises(TypeError, match="expected a Lie group element"):
        jp.interpolate(x, a, 0.5)
    with pytest.raises(TypeError, match="expected a Lie group element"):
        jp.cumprod(a)
    with pytest.raises(TypeError, match=r"expected an array.*use its `\.data`"):
        cls(a)


@by_group
def test_group_where_algebra_expected(cls):
    x = _element(cls)
    for fn in (jp.exp, jp.jr, jp.jl, jp.jr_inv, jp.jl_inv):
        with pytest.raises(TypeError, match=rf"expected a Lie algebra element, got {cls.__name__}"):
            fn(x)
    with pytest.raises(TypeError, match=rf"expected a tangent vector, got group {cls.__name__}"):
        cls.exp(x)
    for method in ("adj", "adjT", "jinvp", "retract"):
        with pytest.raises(TypeError, match=rf"{method}.*group {cls.__name__}"):
            getattr(x, method)(x)
    with pytest.raises(TypeError, match=r"expected an array"):
        x.act(x)
    with pytest.raises(TypeError, match=r"expected an array.*use its `\.data`"):
        cls.algebra(x)


@by_group
def test_algebra_of_another_group(cls):
    other = _other_group(cls)
    x = _element(cls)
    wrong = other.algebra(np.zeros(other.tangent_dim))
    for method in ("adj", "adjT", "jinvp", "retract"):
        with pytest.raises(
            TypeError, match=rf"expected {cls.algebra.__name__}, got {other.algebra.__name__}"
        ):
            getattr(x, method)(wrong)
    with pytest.raises(TypeError, match=rf"expected {cls.algebra.__name__}"):
        cls.exp(wrong)


def test_functional_class_arguments():
    for fn in (jp.identity, jp.from_matrix, jp.random):
        for bad in ("SE3", se3, 3, SE3.identity()):
            with pytest.raises(TypeError, match=r"expected a group class such as SE3"):
                if fn is jp.identity:
                    fn(bad)
                elif fn is jp.from_matrix:
                    fn(bad, np.eye(4))
                else:
                    fn(bad, jax.random.key(0))


@pytest.mark.parametrize("cls", [SO2, SE2], ids=lambda g: g.__name__)
def test_planar_groups_have_no_euler(cls):
    with pytest.raises(TypeError, match=rf"{cls.__name__} has no 3D rotation"):
        jp.euler(_element(cls))


# ------------------------------------------------------------------------------------
# non-array data
# ------------------------------------------------------------------------------------
NON_ARRAYS = [
    pytest.param("abcd", id="str"),
    pytest.param(b"abcd", id="bytes"),
    pytest.param(None, id="None"),
    pytest.param({"data": [0.0, 0.0, 0.0, 1.0]}, id="dict"),
    pytest.param({1.0, 2.0}, id="set"),
    pytest.param(["a", "b", "c", "d"], id="list-of-str"),
    pytest.param(object(), id="object"),
]


@by_group
@pytest.mark.parametrize("bad", NON_ARRAYS)
def test_non_array_group_data(cls, bad):
    with pytest.raises(TypeError, match=rf"{cls.__name__}\(data\): expected an array-like"):
        cls(bad)


@by_algebra
@pytest.mark.parametrize("bad", NON_ARRAYS)
def test_non_array_algebra_data(alg, bad):
    with pytest.raises(TypeError, match=rf"{alg.__name__}\(data\): expected an array-like"):
        alg(bad)


@by_group
def test_non_array_arguments(cls):
    x = _element(cls)
    with pytest.raises(TypeError, match=r"act\(points\): expected an array-like"):
        x.act("xyz")
    with pytest.raises(TypeError, match=r"act\(points\): expected an array-like"):
        x @ None
    with pytest.raises(TypeError, match=r"exp\(a\): expected an array-like"):
        cls.exp({"a": 1})
    with pytest.raises(TypeError, match=r"from_matrix\(matrix\): expected an array-like"):
        cls.from_matrix("eye")
    with pytest.raises(TypeError, match="real floating"):
        cls(np.zeros(cls.storage_dim, np.complex64))


def test_integer_data_is_promoted_to_float():
    x = SO3(np.array([0, 0, 0, 1]))
    assert jnp.issubdtype(x.dtype, jnp.floating)


# ------------------------------------------------------------------------------------
# batch shapes that do not broadcast
# ------------------------------------------------------------------------------------
@by_group
def test_compose_and_act_non_broadcasting_shapes(cls):
    x, y = _element(cls, (3,)), _element(cls, (4,))
    for call in (lambda: x @ y, lambda: jp.compose(x, y)):
        with pytest.raises(
            ValueError, match=rf"{cls.__name__}\.compose.*\(3,\).*\(4,\).*broadcast"
        ):
            call()
    with pytest.raises(ValueError, match=rf"{cls.__name__}\.act\(points\).*broadcast"):
        x.act(np.zeros((4, cls.point_dim)))
    with pytest.raises(ValueError, match=rf"{cls.__name__}\.act\(points\).*broadcast"):
        x @ np.zeros((2, 5, cls.point_dim + 1))


@by_group
@pytest.mark.parametrize(
    "op",
    [
        pytest.param(lambda x, y, t: x.interpolate(y, 0.5), id="interpolate"),
        pytest.param(lambda x, y, t: x.rminus(y), id="rminus"),
        pytest.param(lambda x, y, t: x.retract(t), id="retract"),
        pytest.param(lambda x, y, t: x.adj(t), id="adj"),
        pytest.param(lambda x, y, t: x.adjT(t), id="adjT"),
        pytest.param(lambda x, y, t: x.jinvp(t), id="jinvp"),
        pytest.param(lambda x, y, t: x.interpolate(x, np.full((4,), 0.5)), id="interpolate-t"),
    ],
)
def test_other_operations_non_broadcasting_shapes(cls, op):
    x, y = _element(cls, (3,)), _element(cls, (4,))
    t = np.zeros((4, cls.tangent_dim))
    with pytest.raises(ValueError, match=rf"{cls.__name__}.*\(3,\).*\(4,\).*do not broadcast"):
        op(x, y, t)


def test_algebra_addition_non_broadcasting_shapes():
    with pytest.raises(ValueError, match=r"so3 addition.*\(3,\).*\(4,\).*do not broadcast"):
        so3(np.zeros((3, 3))) + so3(np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"se3 subtraction.*do not broadcast"):
        se3(np.zeros((2, 6))) - se3(np.zeros((5, 6)))


# ------------------------------------------------------------------------------------
# from_matrix with and without the run-time check
# ------------------------------------------------------------------------------------
def _bad_matrix(cls, kind):
    """A matrix that is not an element of ``cls``."""
    n = cls.matrix_dim
    m = np.array(jp.matrix(_element(cls)), np.float64)
    if kind == "sheared":
        m[0, 1] += 0.05  # the rotation block is no longer orthogonal
    elif kind == "reflection":
        m[:, 0] *= -1  # det < 0 (the bottom row [0 … 0 1] is kept)
    elif kind == "bottom-row":
        m[-1, 0] = 0.3
    elif kind == "random":
        m = np.random.default_rng(3).normal(size=(n, n))
    elif kind == "nan":
        m[0, 0] = np.nan
    return m


BAD_KINDS = [
    pytest.param(cls, kind, id=f"{cls.__name__}-{kind}")
    for cls in GROUPS
    for kind in ("sheared", "reflection", "bottom-row", "random", "nan")
    if kind != "bottom-row" or cls.matrix_dim == cls.point_dim + 1
]


@pytest.mark.parametrize("cls,kind", BAD_KINDS)
def test_from_matrix_check_raises_eagerly_and_under_jit(cls, kind):
    m = _bad_matrix(cls, kind)
    msg = rf"not a valid {cls.__name__} matrix"
    with pytest.raises(RuntimeError, match=msg):
        np.asarray(cls.from_matrix(m).data)
    with pytest.raises(RuntimeError, match=msg):
        np.asarray(fast_jit(lambda m: cls.from_matrix(m).data)(m))
    with pytest.raises(RuntimeError, match=msg):  # one bad matrix in a batch
        np.asarray(jp.from_matrix(cls, np.stack([np.eye(cls.matrix_dim), m])).data)


@by_group
@pytest.mark.parametrize("dtype", [np.float32, np.float64], ids=["float32", "float64"])
def test_from_matrix_check_accepts_valid_matrices(cls, dtype):
    m = np.asarray(jp.matrix(_element(cls, (2,))), dtype)
    out = fast_jit(lambda m: cls.from_matrix(m).data)(m)
    assert out.shape == (2, cls.storage_dim) and out.dtype == dtype
    np.testing.assert_allclose(np.asarray(cls(out).matrix()), m, atol=1e-5)


@by_group
def test_from_matrix_without_check_projects(cls):
    n = cls.matrix_dim
    x = _element(cls)
    m = np.asarray(x.matrix(), np.float64)
    noisy = m + 1e-3 * np.random.default_rng(1).normal(size=m.shape)
    if cls.matrix_dim == cls.point_dim + 1:
        noisy[-1] = m[-1]  # keep the homogeneous row
    y = cls.from_matrix(noisy, check=False)
    ym = np.asarray(y.matrix(), np.float64)
    p = cls.point_dim
    block = ym[:p, :p]
    s = np.abs(np.linalg.det(block)) ** (1 / p)
    rot = block / s
    np.testing.assert_allclose(rot.T @ rot, np.eye(p), atol=1e-12, err_msg="projected rotation")
    assert np.linalg.det(rot) > 0
    np.testing.assert_allclose(ym, m, atol=1e-2, err_msg="projection stays near the input")
    # an already valid element is reproduced exactly
    np.testing.assert_allclose(np.asarray(cls.from_matrix(m, check=False).matrix()), m, atol=1e-12)
    assert n == ym.shape[-1]


# ------------------------------------------------------------------------------------
# random() keys, cumprod axes, indexing
# ------------------------------------------------------------------------------------
@by_group
@pytest.mark.parametrize(
    "key",
    [
        pytest.param(0, id="int"),
        pytest.param(np.array([0, 1], np.uint32), id="numpy-uint32"),
        pytest.param("key", id="str"),
        pytest.param(None, id="None"),
        pytest.param(jnp.zeros(2), id="float-array"),
    ],
)
def test_random_with_non_key(cls, key):
    with pytest.raises(
        TypeError, match=rf"{cls.__name__}\.random\(key\): expected a jax\.random key"
    ):
        cls.random(key)
    with pytest.raises(TypeError, match=r"expected a jax\.random key"):
        jp.random(cls, key, (2,))


@by_group
def test_random_accepts_both_key_kinds(cls):
    a = cls.random(jax.random.key(1), (2,))
    b = cls.random(jax.random.PRNGKey(1), (2,))
    assert a.shape == b.shape == (2,)


@by_group
@pytest.mark.parametrize("axis", [2, -3, 5])
def test_cumprod_axis_out_of_range(cls, axis):
    x = _element(cls, (3, 2))
    with pytest.raises(ValueError, match=rf"{cls.__name__}\.cumprod\(axis={axis}\).*\(3, 2\)"):
        x.cumprod(axis)
    with pytest.raises(ValueError, match=r"axis out of range"):
        jp.cumprod(x, axis=axis, left=False)


@by_group
def test_cumprod_of_unbatched_element(cls):
    with pytest.raises(ValueError, match=r"axis out of range for batch shape \(\)"):
        _element(cls).cumprod()


@by_group
def test_indexing_unbatched_element(cls):
    with pytest.raises(IndexError, match=rf"{cls.__name__}\[0\]: the element is unbatched"):
        _element(cls)[0]
    x = _element(cls, (2,))
    assert x[0].shape == () and x[..., 1].shape == () and x[None].shape == (1, 2)


# ------------------------------------------------------------------------------------
# issue 19: fault-injection findings (one regression test per class)
# ------------------------------------------------------------------------------------
UNIT_SLICE = {**QUAT_SLICE, SO2: slice(0, 2), SE2: slice(2, 4)}  # quaternion / (cos, sin)
_JIT_FROM_MATRIX = {cls: fast_jit(lambda m, cls=cls: cls.from_matrix(m).data) for cls in GROUPS}
_JIT_CHECKED = {cls: fast_jit(lambda d, cls=cls: cls(d, check=True).data) for cls in GROUPS}


def _scaled_rotation_matrix(cls, shear, translation, scale=1.0):
    """A ``cls`` matrix whose rotation block is sheared by ``shear`` (relative), with a
    translation of ``translation`` in every coordinate and (Sim3 / RxSO3) a scale."""
    m = np.array(jp.matrix(_element(cls)), np.float64)
    p = cls.point_dim
    s = scale if cls in (jp.Sim3, jp.RxSO3) else 1.0
    rot = m[:p, :p] / np.cbrt(np.linalg.det(m[:p, :p])) if p == 3 else m[:p, :p]
    rot = rot / abs(np.linalg.det(rot)) ** (1 / p)
    rot[0, 1] += shear
    m[:p, :p] = s * rot
    if cls.matrix_dim == p + 1:
        m[:p, p] = translation
    return m


@by_group
def test_from_matrix_check_looks_at_the_rotation_block_alone(cls):
    """Defect 4: the tolerance once included the translation (1e-9·max|M|), so a rotation
    sheared by 5e-3 with a UTM-sized translation of 5e6 passed and was silently projected."""
    jitted = _JIT_FROM_MATRIX[cls]
    for scale in (1e-3, 1.0, 1e3):
        bad = _scaled_rotation_matrix(cls, 5e-3, 5e6, scale)
        with pytest.raises(RuntimeError, match=rf"not a valid {cls.__name__} matrix"):
            cls.from_matrix(bad)
        with pytest.raises(RuntimeError, match=rf"not a valid {cls.__name__} matrix"):
            np.asarray(jitted(bad))
        good = _scaled_rotation_matrix(cls, 0.0, 5e6, scale)
        out = np.asarray(jitted(good))
        np.testing.assert_allclose(np.asarray(cls(out).matrix()), good, rtol=1e-12, atol=1e-9)
    # the tolerance is relative to the rotation block's own size (Sim3: the scaled rotation)
    tiny = _scaled_rotation_matrix(cls, 1e-4, 0.0, 1e-6)
    if cls in (jp.Sim3, jp.RxSO3):
        with pytest.raises(RuntimeError, match="relative 1e-09"):
            cls.from_matrix(tiny)
    # float32 with a 5e6 translation: a valid matrix is accepted
    good32 = np.asarray(_scaled_rotation_matrix(cls, 0.0, 5e6), np.float32)
    assert cls.from_matrix(good32).dtype == np.float32


@pytest.mark.parametrize("kind", [*GROUPS, *ALGEBRAS], ids=lambda c: c.__name__)
def test_out_of_range_indices_raise_and_iteration_ends(kind):
    """Defect 5: JAX clamps out-of-range indices, so X[5] returned X[1] and list(X),
    ``for x in X`` and np.asarray(X) never ended."""
    import itertools

    dim = kind.storage_dim if issubclass(kind, jp.LieGroup) else kind.tangent_dim
    data = np.arange(2 * 3 * dim, dtype=np.float64).reshape(2, 3, dim)
    x = kind(data)
    for idx in (2, -3, 5, (0, 3), (1, -4), (..., 3), (Ellipsis, -4), [0, 2], (0, [1, 3])):
        with pytest.raises(IndexError, match=r"out of range for batch axis"):
            x[idx]
    with pytest.raises(IndexError, match="too many indices"):
        x[0, 0, 0]
    np.testing.assert_array_equal(np.asarray(x[1, -1].data), data[1, -1])
    np.testing.assert_array_equal(np.asarray(x[..., 2].data), data[:, 2])
    np.testing.assert_array_equal(np.asarray(x[-2].data), data[0])
    items = list(itertools.islice(iter(x), 10))
    assert len(items) == 2 == len(x)
    np.testing.assert_array_equal(np.asarray(items[1].data), data[1])
    assert len([y for y in x[0]]) == 3
    assert np.asarray(x).shape == data.shape  # np.asarray(X) is the stored data
    np.testing.assert_array_equal(np.asarray(x), data)
    with pytest.raises(TypeError, match=rf"iteration over an unbatched {kind.__name__}"):
        iter(x[0, 0])
    with pytest.raises(TypeError, match=r"len\(\) of an unbatched"):
        len(x[0, 0])


def _invalid_data(cls, kind):
    d = random_group_data(np.random.default_rng(5), cls, (2,))
    u = UNIT_SLICE[cls]
    if kind == "zero":
        d[1, u] = 0.0
    elif kind == "nan":
        d[0, 0] = np.nan
    elif kind == "inf":
        d[1, -1] = np.inf
    elif kind == "non-unit":
        d[0, u] *= 1.001
    elif kind == "scale-zero":
        d[1, DATA_SCALE_INDEX[cls]] = 0.0
    elif kind == "scale-negative":
        d[0, DATA_SCALE_INDEX[cls]] = -2.0
    return d


CHECK_KINDS = {
    "zero": r"zero (quaternion|\[cos θ, sin θ\])",
    "nan": "non-finite",
    "inf": "non-finite",
    "non-unit": r"non-unit norm.*normalize\(\)",
    "scale-zero": r"scale s must be > 0",
    "scale-negative": r"scale s must be > 0",
}
CHECK_CASES = [
    pytest.param(cls, kind, id=f"{cls.__name__}-{kind}")
    for cls in GROUPS
    for kind in CHECK_KINDS
    if not kind.startswith("scale") or cls in DATA_SCALE_INDEX
]


@pytest.mark.parametrize("cls,kind", CHECK_CASES)
def test_checked_constructor_rejects_invalid_elements(cls, kind):
    """Decide-and-document: G(data) checks shapes only (a zero quaternion gives NaN from
    log/normalize/rminus, a scale ≤ 0 NaN from log/inv); G(data, check=True) rejects them,
    eagerly with a one-line message and under jit through eqx.error_if."""
    bad = _invalid_data(cls, kind)
    msg = rf"{cls.__name__}\(data, check=True\): .*{CHECK_KINDS[kind]}"
    with pytest.raises(jp.InvalidValueError, match=msg) as err:
        cls(bad, check=True)
    assert "\n" not in str(err.value) and isinstance(err.value, (ValueError, RuntimeError))
    with pytest.raises(RuntimeError, match=msg):
        np.asarray(_JIT_CHECKED[cls](bad))


@by_group
def test_checked_constructor_accepts_valid_elements(cls):
    good = random_group_data(np.random.default_rng(6), cls, (2,))
    np.testing.assert_array_equal(np.asarray(_JIT_CHECKED[cls](good)), good)
    np.testing.assert_array_equal(np.asarray(cls(good, check=True).data), good)
    cls(np.asarray(good, np.float32), check=True)
    cls(np.zeros((0, cls.storage_dim)), check=True)  # an empty batch has nothing to check
    # a slightly non-unit rotation passes with a looser tolerance
    off = good.copy()
    off[:, UNIT_SLICE[cls]] *= 1 + 1e-7
    with pytest.raises(jp.InvalidValueError):
        cls(off, check=True)
    cls(off, check=True, tol=1e-6)


@by_algebra
def test_checked_algebra_rejects_non_finite(alg):
    a = np.zeros((2, alg.tangent_dim))
    alg(a, check=True)
    a[1, 0] = np.nan
    with pytest.raises(jp.InvalidValueError, match=rf"{alg.__name__}\(data, check=True\)"):
        alg(a, check=True)


@pytest.mark.parametrize("cls", GROUPS, ids=lambda g: g.__name__)
@pytest.mark.parametrize("factor", [1e200, 1e-200], ids=["x1e200", "x1e-200"])
def test_extreme_quaternion_magnitudes(cls, factor):
    """Extreme magnitudes: q·1e200 overflowed |q|² (normalize gave 0, log 0) and q·1e-200
    underflowed it (log took the small-angle branch); normalize and log of any nonzero
    finite quaternion / (cos, sin) pair now act on its direction."""
    good = random_group_data(np.random.default_rng(7), cls, (3,))
    big = good.copy()
    big[:, UNIT_SLICE[cls]] *= factor
    x, ref = cls(big), cls(good)
    n = x.normalize()
    np.testing.assert_allclose(np.asarray(n.data), good, rtol=1e-13, atol=1e-15)
    if cls in (jp.SO3, jp.RxSO3, jp.SO2):  # log is invariant under scaling the rotation
        np.testing.assert_allclose(
            np.asarray(x.log().data), np.asarray(ref.log().data), rtol=1e-12, atol=1e-15
        )
    np.testing.assert_allclose(
        np.asarray(n.rminus(ref)), np.zeros((3, cls.tangent_dim)), atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(n.interpolate(ref, 0.5).data), good, rtol=1e-12, atol=1e-12
    )


def test_so3_exp_of_huge_and_tiny_rotation_vectors():
    """so3.exp of 1e200 once overflowed θ² and returned NaN; any finite rotation vector now
    gives a unit quaternion about its axis (the angle modulo 2π carries no information there:
    documented)."""
    phis = np.array([[1e200, 0, 0], [1e200, -1e200, 3e199], [0, 0, 1e300], [1e-200, 0, 2e-200]])
    q = np.asarray(SO3.exp(phis).data)
    assert np.all(np.isfinite(q))
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, rtol=1e-14)
    axes = phis / np.abs(phis).max(-1, keepdims=True)
    np.testing.assert_allclose(np.cross(q[:, :3], axes), 0, atol=1e-15)  # along the axis
    np.testing.assert_allclose(q[3], [5e-201, 0, 1e-200, 1.0], rtol=1e-15)
    q32 = np.asarray(SO3.exp(np.array([3e30, 1e30, 0], np.float32)).data)
    assert q32.dtype == np.float32 and abs(np.linalg.norm(q32) - 1) < 1e-6


def test_series_sincos_stays_bounded_far_beyond_its_range():
    """The Cody–Waite reduction of series.sincos is exact to |x| ≈ 1.6e6; far beyond, the
    polynomials once returned values of 1e300 (sinc(1e300) = -inf, feeding SE3.exp)."""
    from jaxpose.lie import series

    x = np.array([1e7, 1e10, 1e20, 1e100, 1e300])
    s, c = (np.asarray(v) for v in series.sincos(x))
    assert np.all(np.abs(s) <= 1) and np.all(np.abs(c) <= 1)
    np.testing.assert_allclose(s[:2], np.sin(x[:2]), atol=1e-6)
    assert np.isfinite(np.asarray(series.sinc(1e300)))


# ------------------------------------------------------------------------------------
# issue 15: what a new user tripped on (printing, identity(4), ==)
# ------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", [*GROUPS, *ALGEBRAS], ids=lambda c: c.__name__)
def test_repr_shows_values_and_eq_is_elementwise(kind):
    dim = kind.storage_dim if issubclass(kind, jp.LieGroup) else kind.tangent_dim
    data = np.arange(3 * dim, dtype=np.float64).reshape(3, dim) + 0.25
    x = kind(data)
    text = repr(x)
    assert text.startswith(f"{kind.__name__}([[") and "0.25" in text and "float64" in text
    row = np.array2string(data[0], separator=", ")
    assert str(x[0]) == f"{kind.__name__}({row}, dtype=float64)"
    seen = []
    fast_jit(lambda d: seen.append(repr(kind(d))) or d)(data)  # traced: no values, no error
    assert seen and seen[0].startswith(f"{kind.__name__}(")
    other = data.copy()
    other[1, -1] += 1
    eq = x == kind(other)
    np.testing.assert_array_equal(np.asarray(eq), [True, False, True])
    np.testing.assert_array_equal(np.asarray(x != kind(other)), [False, True, False])
    assert np.asarray(x[0] == x[0]).shape == () and bool(x[0] == x[0])
    assert (x == data) is False  # another type: not equal (no elementwise array comparison)
    with pytest.raises(ValueError, match="do not broadcast"):
        x == kind(np.zeros((2, dim)))


@by_group
def test_int_batch_shapes(cls):
    assert cls.identity(4).shape == (4,) == jp.identity(cls, 4).shape
    assert cls.random(jax.random.key(0), 3).shape == (3,)
    assert cls.identity().broadcast_to(2).shape == (2,)
    with pytest.raises(TypeError, match=rf"{cls.__name__}\.identity\(shape\): expected an int"):
        cls.identity("4")
    with pytest.raises(ValueError, match="negative dimension"):
        cls.identity(-1)


@pytest.mark.parametrize("cls", [jp.Sim3, jp.RxSO3, SO2, SE2], ids=lambda g: g.__name__)
def test_from_matrix_of_extreme_scales(cls):
    """Same class in from_matrix: det(s·R) of a 1e200 scale overflowed (Sim3/RxSO3 scale
    inf, rotation 0) and SE2/SO2's c² + s² overflowed to a [0, 0] rotation without check."""
    x = _element(cls, (2,))
    p = cls.point_dim
    for f in (1e200, 1e-200):
        m = np.array(x.matrix(), np.float64)
        m[:, :p, :p] *= f
        y = cls.from_matrix(m, check=cls in (jp.Sim3, jp.RxSO3))
        np.testing.assert_allclose(
            np.asarray(y.scale()),
            np.asarray(x.scale()) * (f if cls in (jp.Sim3, jp.RxSO3) else 1.0),
            rtol=1e-13,
        )
        np.testing.assert_allclose(
            np.asarray(y.rotation().matrix()), np.asarray(x.rotation().matrix()), atol=1e-14
        )


@pytest.mark.parametrize("kind", [SO3, se3], ids=lambda c: c.__name__)
def test_out_of_range_concrete_jax_array_indices_raise(kind):
    """Concrete (non-traced) JAX integer indices were not bounds-checked: X[jnp.array(5)]
    silently returned X[2] (JAX's gather clamps). They are checked like NumPy indices; a
    traced index (under jit) has no known value and keeps JAX's documented clamping."""
    dim = kind.storage_dim if issubclass(kind, jp.LieGroup) else kind.tangent_dim
    data = np.arange(3 * 4 * dim, dtype=np.float64).reshape(3, 4, dim)
    x = kind(data)
    for idx, bad in ((jnp.array(5), 5), (jnp.array(-4), -4), (jnp.array([0, 7]), 7),
                     ((0, jnp.array([1, 4])), 4), ((..., jnp.array(-5)), -5),
                     ((jnp.array(1), jnp.array(4)), 4)):
        with pytest.raises(IndexError, match=rf"index {bad} is out of range for batch axis"):
            x[idx]
    # in range: the same values as NumPy indexing of the data
    for idx, expected in ((jnp.array(2), data[2]), (jnp.array(-3), data[0]),
                          (jnp.array([2, 0]), data[[2, 0]]),
                          ((jnp.array(1), jnp.array(-1)), data[1, 3]),
                          ((..., jnp.array([3, 0])), data[:, [3, 0]])):
        np.testing.assert_array_equal(np.asarray(x[idx].data), expected)
    # a boolean mask is no integer index
    np.testing.assert_array_equal(np.asarray(x[jnp.array([True, False, True])].data),
                                  data[[0, 2]])
    # traced: no value to check, JAX clamps (documented)
    clamped = jax.jit(lambda y, i: y[i])(x, jnp.array(5))
    np.testing.assert_array_equal(np.asarray(clamped.data), data[2])


def test_from_rotation_translation_promotes_like_compose_and_identity_needs_a_float():
    """A float64 translation was rounded to a float32 rotation's dtype (1 + 1e-9 → 1.0);
    identity(dtype=int32) returned float64."""
    from jaxpose.lie import SE3, SO3

    rot = SO3.identity(dtype=jnp.float32)
    t64 = np.array([1.0 + 1e-9, 0.0, 0.0])
    x = SE3.from_rotation_translation(rot, t64)
    y = SE3.identity(dtype=jnp.float32).compose(SE3(np.concatenate([t64, [0, 0, 0, 1.0]])))
    assert x.dtype == y.dtype == jnp.float64
    assert float(x.translation()[0]) - 1.0 == pytest.approx(1e-9, rel=1e-6)
    assert SE3.from_rotation_translation(rot, [1.0, 2.0, 3.0]).dtype == jnp.float32
    with pytest.raises(TypeError, match=r"SO3.identity\(dtype=.*expected a floating dtype"):
        SO3.identity(dtype=jnp.int32)
