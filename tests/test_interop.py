"""jaxpose.interop against the peers themselves: jaxlie's and PyPose's own matrices, Exp,
actions and compositions must agree with jaxpose's on the converted objects."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose as jp
from jaxpose import interop

jax.config.update("jax_enable_x64", True)

pytestmark = pytest.mark.peer
KEY = jax.random.PRNGKey(7)
JAXLIE_GROUPS = [(jp.SO3, jp.so3), (jp.SE3, jp.se3), (jp.SO2, jp.so2), (jp.SE2, jp.se2)]


def _tangent(alg, key, batch, scale=1.0):
    dim = {jp.so3: 3, jp.se3: 6, jp.sim3: 7, jp.rxso3: 4, jp.so2: 1, jp.se2: 3}[alg]
    return alg(scale * jax.random.normal(key, (*batch, dim)))


# ----------------------------------------------------------------------------------
# jaxlie
# ----------------------------------------------------------------------------------
@pytest.mark.parametrize("group,alg", JAXLIE_GROUPS, ids=lambda c: c.__name__)
def test_jaxlie_matches_matrices_exp_action_and_compose(group, alg):
    jaxlie = pytest.importorskip("jaxlie")
    JL = getattr(jaxlie, group.__name__)
    k1, k2, k3 = jax.random.split(KEY, 3)
    a, b = _tangent(alg, k1, (4, 3), scale=0.5), _tangent(alg, k2, (4, 3))
    n = 3 if group in (jp.SO3, jp.SE3) else 2
    p = jax.random.normal(k3, (4, 3, n))
    assert float(jnp.max(jnp.abs(a.data))) < 1.7  # |θ| < π: Log returns the same tangent

    @jax.jit
    def both(a, b, p):  # one compilation per group: jaxlie's ops and jaxpose's side by side
        X, Y = a.exp(), b.exp()
        JX, JY = interop.to_jaxlie(X), interop.to_jaxlie(Y)
        peer = (JX.as_matrix(), JL.exp(a.data).as_matrix(), JX.log(), (JX @ JY).as_matrix(),
                JX.apply(p), interop.from_jaxlie(JX).data)
        ours = (X.matrix(), X.matrix(), a.data, (X @ Y).matrix(), X @ p, X.data)
        return JX, peer, ours

    JX, peer, ours = both(a, b, p)
    assert isinstance(JX, JL) and JX.parameters().shape == a.exp().data.shape
    names = ["matrix", "Exp of the same tangent", "Log", "compose", "act", "round trip"]
    for name, x, y in zip(names, peer, ours):
        np.testing.assert_allclose(x, y, atol=1e-10, err_msg=name)
    np.testing.assert_array_equal(peer[-1], ours[-1])  # a permutation: exact
    assert type(interop.from_jaxlie(JX)) is group


def test_jaxlie_storage_order_is_explicit():
    jaxlie = pytest.importorskip("jaxlie")
    q = jnp.array([0.1, 0.2, 0.3, 0.9])  # [qx, qy, qz, qw], not normalised: pure reindexing
    t = jnp.array([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(interop.to_jaxlie(jp.SO3(q)).wxyz, [0.9, 0.1, 0.2, 0.3])
    np.testing.assert_array_equal(
        interop.to_jaxlie(jp.SE3(jnp.concatenate([t, q]))).wxyz_xyz,
        [0.9, 0.1, 0.2, 0.3, 1.0, 2.0, 3.0],
    )
    np.testing.assert_array_equal(
        interop.to_jaxlie(jp.SE2(jnp.array([1.0, 2.0, 0.6, 0.8]))).unit_complex_xy,
        [0.6, 0.8, 1.0, 2.0],
    )
    X = interop.from_jaxlie(jaxlie.SE3(jnp.array([0.9, 0.1, 0.2, 0.3, 1.0, 2.0, 3.0])))
    np.testing.assert_array_equal(X.data, [1.0, 2.0, 3.0, 0.1, 0.2, 0.3, 0.9])
    np.testing.assert_array_equal(X.rotation().wxyz(), [0.9, 0.1, 0.2, 0.3])


def test_jaxlie_conversion_jits_vmaps_differentiates_float32():
    jaxlie = pytest.importorskip("jaxlie")
    p = jnp.array([0.3, -1.0, 2.0], dtype=jnp.float32)

    def via_jaxlie(v):
        return jnp.sum(interop.to_jaxlie(jp.so3(v).exp()).apply(p) ** 2)

    def native(v):
        return jnp.sum((jp.so3(v).exp() @ p) ** 2)

    v = jax.random.normal(KEY, (5, 3), dtype=jnp.float32)
    grads = jax.jit(lambda v: [jax.vmap(jax.grad(f))(v) for f in (via_jaxlie, native)])
    g1, g2 = grads(v)
    assert g1.dtype == jnp.float32
    np.testing.assert_allclose(g1, g2, rtol=2e-5, atol=2e-5)
    Z = jax.jit(interop.from_jaxlie)(jaxlie.SO3.exp(v))
    assert Z.data.dtype == jnp.float32
    np.testing.assert_allclose(Z.data, jp.so3(v).exp().data, atol=1e-6)


def test_jaxlie_bad_input():
    pytest.importorskip("jaxlie")
    with pytest.raises(TypeError, match=r"to_jaxlie\(x\).*Sim3.*jaxlie has no such group"):
        interop.to_jaxlie(jp.Sim3.identity())
    with pytest.raises(TypeError, match=r"to_jaxlie\(x\)"):
        interop.to_jaxlie(jp.so3(jnp.zeros(3)))
    with pytest.raises(TypeError, match=r"from_jaxlie\(x\): expected a jaxlie"):
        interop.from_jaxlie(jnp.zeros(4))


# ----------------------------------------------------------------------------------
# PyPose / torch
# ----------------------------------------------------------------------------------
PP_PAIRS = [(jp.SO3, jp.so3), (jp.SE3, jp.se3), (jp.Sim3, jp.sim3), (jp.RxSO3, jp.rxso3)]


@pytest.mark.parametrize("group,alg", PP_PAIRS, ids=lambda c: c.__name__)
def test_pypose_round_trip_and_peer_operations(group, alg):
    pp = pytest.importorskip("pypose")
    torch = pytest.importorskip("torch")
    k1, k2 = jax.random.split(KEY)
    a, b = _tangent(alg, k1, (2, 3), scale=0.5), _tangent(alg, k2, (2, 3), scale=0.5)
    X, Y, XY = jax.jit(lambda a, b: (a.exp(), b.exp(), a.exp() @ b.exp()))(a, b)
    La, LX, LY = interop.to_pypose(a), interop.to_pypose(X), interop.to_pypose(Y)
    assert La.ltype == getattr(pp, f"{alg.__name__}_type")
    assert LX.ltype == getattr(pp, f"{group.__name__}_type") and LX.dtype == torch.float64
    # PyPose's own Exp / compose / Log on the converted tensors match jaxpose's (on an
    # accelerator the tensors share the device's memory: .cpu() before numpy).
    np.testing.assert_allclose(La.Exp().tensor().cpu().numpy(), X.data, atol=1e-12)
    np.testing.assert_allclose((LX * LY).tensor().cpu().numpy(), XY.data, atol=1e-12)
    np.testing.assert_allclose(LX.Log().tensor().cpu().numpy(), a.data, atol=1e-10)
    for src in (X, a):
        back = interop.from_pypose(interop.to_pypose(src))
        assert type(back) is type(src)
        np.testing.assert_array_equal(back.data, src.data)
    # A gradient-carrying LieTensor converts (detached), float32 cast on request.
    Z = interop.from_pypose(interop.to_pypose(X, requires_grad=True), dtype=jnp.float32)
    assert Z.data.dtype == jnp.float32


def test_torch_arrays_and_bad_input():
    torch = pytest.importorskip("torch")
    pytest.importorskip("pypose")
    x32 = jnp.arange(6.0, dtype=jnp.float32).reshape(2, 3)
    t = interop.to_torch(x32)
    assert isinstance(t, torch.Tensor) and t.dtype == torch.float32 and t.shape == (2, 3)
    np.testing.assert_array_equal(t.cpu().numpy(), x32)
    np.testing.assert_array_equal(interop.from_torch(t * 2), 2 * x32)
    X = jp.SE3.random(KEY, (3,))
    np.testing.assert_array_equal(interop.to_torch(X).cpu().numpy(), X.data)
    with pytest.raises(TypeError, match=r"to_pypose\(x\).*SE2"):
        interop.to_pypose(jp.SE2.identity())
    with pytest.raises(TypeError, match=r"from_pypose\(x\): expected a pypose.LieTensor"):
        interop.from_pypose(torch.zeros(7))
    with pytest.raises(TypeError, match=r"from_torch\(t\): expected a torch.Tensor"):
        interop.from_torch(np.zeros(3))
    with pytest.raises(TypeError, match=r"to_torch\(x\): got a traced value"):
        jax.jit(interop.to_torch)(x32)


def test_from_torch_refuses_integers_that_would_wrap_without_x64():
    """With x64 off an int64 2**40 came back as 0 (JAX narrows to int32 by wrapping)."""
    torch = pytest.importorskip("torch")
    before = jax.config.jax_enable_x64
    try:
        jax.config.update("jax_enable_x64", False)
        with pytest.raises(ValueError, match=r"from_torch\(t\): int64 values beyond int32"):
            interop.from_torch(torch.tensor([2**40, 1]))
        small = interop.from_torch(torch.tensor([2**30, -5]))
        assert small.dtype == jnp.int32 and small.tolist() == [2**30, -5]
        np.testing.assert_array_equal(interop.from_torch(torch.tensor([2**40]),
                                                         dtype=jnp.float32), [2.0**40])
        # an explicit integer dtype that JAX narrows (int64 → int32) wrapped silently: 0
        with pytest.raises(ValueError, match=r"int64 values beyond int32's range.*x64"):
            interop.from_torch(torch.tensor([2**40, 5]), dtype=np.int64)
    finally:
        jax.config.update("jax_enable_x64", before)
    with pytest.raises(ValueError, match=r"beyond int32's range.*wider or a float dtype"):
        interop.from_torch(torch.tensor([2**40, 5]), dtype=np.int32)


def test_from_torch_reads_bfloat16_and_lazy_views():
    """bfloat16 (which to_torch produces) raised "unsupported ScalarType BFloat16"; a lazy
    conjugate or negative view raised torch's "Can't call numpy()"."""
    torch = pytest.importorskip("torch")
    x = jnp.asarray([1.5, -2.25, 3e3], jnp.bfloat16)
    back = interop.from_torch(interop.to_torch(x))
    assert back.dtype == jnp.bfloat16
    np.testing.assert_array_equal(np.asarray(back, np.float32), np.asarray(x, np.float32))
    z = torch.tensor([1 + 2j, 3 - 1j])
    np.testing.assert_array_equal(interop.from_torch(z.conj()), [1 - 2j, 3 + 1j])
    np.testing.assert_array_equal(interop.from_torch(torch.tensor([1.0, 2.0])._neg_view()),
                                  [-1.0, -2.0])
