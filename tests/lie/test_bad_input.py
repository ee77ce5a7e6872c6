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

from .conftest import ALGEBRAS, GROUPS, fast_jit, random_group_data

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
