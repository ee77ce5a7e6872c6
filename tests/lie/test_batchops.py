"""identity_like / random_like / cumops and the Lie-aware assert_close, against
closed forms, sequential products and PyPose (peer)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose as jp
from jaxpose.testing import assert_close

jax.config.update("jax_enable_x64", True)


def test_identity_like_and_random_like_keep_type_shape_dtype():
    x = jp.SE3.random(jax.random.PRNGKey(0), (2, 3))
    ident = jp.identity_like(x)
    assert type(ident) is jp.SE3 and ident.shape == (2, 3)
    np.testing.assert_array_equal(ident.matrix(), np.broadcast_to(np.eye(4), (2, 3, 4, 4)))
    a = jp.so3(jnp.ones((4, 3), jnp.float32))
    assert jp.identity_like(a).data.dtype == jnp.float32
    assert not np.any(np.asarray(jp.identity_like(a).data))
    r = jp.random_like(a, jax.random.PRNGKey(1), sigma=0.0)
    assert type(r) is jp.so3 and r.shape == (4,) and not np.any(np.asarray(r.data))
    g = jp.random_like(x, jax.random.PRNGKey(2), sigma=0.5)
    assert type(g) is jp.SE3 and g.shape == (2, 3)
    np.testing.assert_allclose(np.linalg.norm(g.data[..., 3:], axis=-1), 1.0, atol=1e-12)
    with pytest.raises(TypeError, match=r"identity_like\(x\)"):
        jp.identity_like(jnp.zeros(3))


def test_cumops_equals_sequential_products_any_axis():
    x = jp.SO3.random(jax.random.PRNGKey(3), (3, 5))
    fwd = jp.cumops(x, lambda a, b: a @ b, axis=1)
    m = np.asarray(x.matrix())
    for i in range(3):
        acc = np.eye(3)
        for k in range(5):
            acc = acc @ m[i, k]
            np.testing.assert_allclose(fwd[i, k].matrix(), acc, atol=1e-12)
    assert_close(jp.cumops(x, lambda a, b: b @ a, axis=-1), x.cumprod(axis=1))
    # algebra addition is associative: a cumulative sum
    v = jp.se3(jax.random.normal(jax.random.PRNGKey(4), (6, 6)))
    np.testing.assert_allclose(jp.cumops(v, lambda a, b: jp.se3(a.data + b.data)).data,
                               np.cumsum(np.asarray(v.data), 0), atol=1e-12)
    # jit and grad through the scan
    f = jax.jit(lambda d: jnp.sum(jp.cumops(jp.se3(d), lambda a, b: jp.se3(a.data * b.data))
                                  .data))
    d = np.linspace(0.5, 1.5, 12).reshape(2, 6)
    np.testing.assert_allclose(jax.grad(f)(d), [d[1] + 1, d[0]], atol=1e-12)
    with pytest.raises(ValueError, match=r"cumops\(axis=2\)"):
        jp.cumops(x, lambda a, b: a @ b, axis=2)
    with pytest.raises(TypeError, match=r"cumops\(op\)"):
        jp.cumops(x, lambda a, b: a.data)


def test_assert_close_lie_aware_and_names_the_path():
    x = jp.SE3.random(jax.random.PRNGKey(5), (4,))
    flipped = jp.SE3(jnp.concatenate([x.data[:, :3], -x.data[:, 3:]], -1))  # q → −q
    assert_close({"pose": x, "v": jnp.ones(2)}, {"pose": flipped, "v": jnp.ones(2)})
    moved = x @ jp.se3(jnp.full((4, 6), 1e-3)).exp()
    with pytest.raises(AssertionError, match=r"\['pose'\]"):
        assert_close({"pose": moved}, {"pose": x})
    assert_close(moved, x, rtol=0.0, atol=1e-2)
    with pytest.raises(AssertionError, match="types differ"):
        assert_close(jp.SO3.identity(), jp.so3(jnp.zeros(3)))
    with pytest.raises(AssertionError, match="assert_close at value"):
        assert_close(jnp.ones(3, jnp.float32), jnp.ones(3, jnp.float32) + 1e-4)
    with pytest.raises(ValueError, match="both or neither"):
        assert_close(x, x, rtol=1e-3)


@pytest.mark.peer
def test_cumops_matches_pypose():
    pp = pytest.importorskip("pypose")
    import torch

    x = jp.SE3.random(jax.random.PRNGKey(6), (7,))
    theirs = pp.cumops(pp.SE3(torch.tensor(np.asarray(x.data))), 0, lambda a, b: a @ b)
    assert_close(jp.cumops(x, lambda a, b: a @ b), jp.SE3(theirs.tensor().numpy()))
