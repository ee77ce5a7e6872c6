"""NumPy evaluation of structural/integer primitives against XLA (the primitive bound)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from jaxpose.optim import _sparsity
from jaxpose.optim._host_eval import UnsupportedPrimitiveError, eval_jaxpr, host_eval

X = np.arange(24, dtype=np.int32).reshape(2, 3, 4) - 7
CASES = {
    "reshape": lambda x: x.reshape(6, 4),
    "broadcast_in_dim": lambda x: lax.broadcast_in_dim(x[:, :1], (2, 5, 3, 4), (0, 2, 3)),
    "transpose": lambda x: jnp.transpose(x, (2, 0, 1)),
    "squeeze_expand": lambda x: jnp.expand_dims(x[:, 1], 1),
    "rev": lambda x: lax.rev(x, (0, 2)),
    "slice_strided": lambda x: lax.slice(x, (0, 1, 0), (2, 3, 4), (1, 1, 3)),
    "concatenate": lambda x: jnp.concatenate([x, -x], 2),
    "stack": lambda x: jnp.stack([x, x + 1], 1),
    "split": lambda x: jnp.split(x, [1, 3], 2),
    "pad_negative_interior": lambda x: lax.pad(
        x, np.int32(-1), ((1, -1, 2), (0, 0, 0), (-1, 2, 1))),
    "dynamic_slice_clamped": lambda x: lax.dynamic_slice(x, (1, 2, -3), (2, 2, 3)),
    "dynamic_update_slice_clamped": lambda x: lax.dynamic_update_slice(
        x, -x[:, :2, :2], (np.int32(5), np.int32(0), np.int32(3))),
    "integer_division": lambda x: (x // 3, lax.div(x, np.int32(3)), lax.rem(x, np.int32(3))),
    "compare_select": lambda x: jnp.where(x > 2, x, lax.neg(x)) * 2 - jnp.maximum(x, 0),
    "clamp_abs_sign": lambda x: (lax.clamp(np.int32(-2), x, np.int32(5)), jnp.abs(x), jnp.sign(x)),
    "iota_logic": lambda x: (lax.iota(np.int32, 4) + x) & 3 | (x ^ 5),
    "convert": lambda x: x.astype(np.int64) * 3,
    "nested_jit": lambda x: jax.jit(lambda y: jnp.where(y < 0, y, 7))(x),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_host_evaluation_equals_xla(name):
    closed = jax.make_jaxpr(CASES[name])(X)
    want = jax.jit(CASES[name])(X)
    got = eval_jaxpr(closed.jaxpr, closed.consts, [X])
    for g, w in zip(got, jax.tree.leaves(want), strict=True):
        assert g.dtype == w.dtype and g.shape == w.shape
        np.testing.assert_array_equal(g, np.asarray(w))


def test_unmodelled_primitives_are_refused():
    closed = jax.make_jaxpr(lambda x: jnp.cumsum(x))(X[0, 0])
    with pytest.raises(UnsupportedPrimitiveError):
        host_eval(closed.jaxpr.eqns[0], [X[0, 0]])


@pytest.mark.parametrize("fn, arg", [
    (lambda x: lax.div(x, np.int32(0)), X),  # XLA defines x / 0 its own way
    (lambda x: lax.rem(x, np.int32(0)), X),
    (lambda x: x.astype(np.int32), np.array([1.5, np.nan])),  # NaN → int
])
def test_cases_with_xla_specific_results_are_left_to_xla(fn, arg):
    closed = jax.make_jaxpr(fn)(arg)
    with pytest.raises(UnsupportedPrimitiveError):
        host_eval(closed.jaxpr.eqns[-1], [arg, np.int32(0)][:len(closed.jaxpr.eqns[-1].invars)])


def test_pattern_of_structural_residual_compiles_nothing(monkeypatch):
    """A residual of slices, reshapes, concatenations and integer-indexed reads is
    analysed without a single eager XLA compilation (the slow path before NumPy rules)."""
    def refuse(*args, **kwargs):
        raise AssertionError("bound eagerly")

    monkeypatch.setattr(_sparsity, "_bind", refuse)

    def f(x):
        a = x.reshape(5, 4)
        b = jnp.concatenate([a[:, 1:], a[:, :1] ** 2], 1)
        return (b[2] * a[3, 0] + jnp.pad(a[:, 2], 1)[1:5].sum()).reshape(-1)

    _sparsity._CACHE.clear()
    _, pattern = _sparsity.jacobian_pattern(f, jnp.zeros(20))
    want = jax.jacfwd(f)(jnp.asarray(np.random.default_rng(0).normal(size=20))) != 0
    np.testing.assert_array_equal(pattern.toarray(), np.asarray(want))
