"""Tangent-space calculus over pytrees mixing Lie groups and arrays, and the optax adapter.

References are independent of the code under test: group leaves are checked as matrices
(storage layout → matrix, scipy expm), derivatives against central finite differences taken
through the retraction, and the pose-averaging optimum against a mean computed with scipy's
matrix exponential / logarithm.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.linalg
from jax.flatten_util import ravel_pytree

from jaxpose.lie import SE2, SE3, SO2, SO3, LieGroup, RxSO3, Sim3, manifold

from .conftest import (
    COSSIN_SLICE,
    QUAT_SLICE,
    assert_close,
    fast_jit,
    random_group_data,
    random_tangent,
    ref_exp_matrix,
    ref_hat,
    ref_matrix,
    ref_vee,
)

is_group = manifold.is_group


def _params(seed: int = 0, dtype=np.float64):
    """A pytree mixing groups (several batch shapes) and arrays: dicts, tuples, lists."""
    rng = np.random.default_rng(seed)

    def g(cls, shape):
        return cls(np.asarray(random_group_data(rng, cls, shape), dtype))

    return {
        "pose": g(SE3, (3,)),
        "pair": (g(SO3, ()), g(SO2, (2,))),
        "nested": {
            "v": np.asarray(rng.normal(size=4), dtype),
            "sim": g(Sim3, ()),
            "list": [g(RxSO3, ()), g(SE2, (1,))],
        },
        "scalar": np.asarray(rng.normal(), dtype),
    }


def _random_tangent(params, seed: int = 1, max_angle: float = 2.0):
    rng = np.random.default_rng(seed)

    def one(x):
        if is_group(x):
            return np.asarray(random_tangent(rng, type(x), x.shape, max_angle=max_angle), x.dtype)
        return np.asarray(rng.normal(size=np.shape(x)), np.asarray(x).dtype)

    return jax.tree.map(one, params, is_leaf=is_group)


def _assert_trees_close(a, b, f64=1e-10, err_msg=""):
    la, ta = jax.tree.flatten(a, is_leaf=is_group)
    lb, tb = jax.tree.flatten(b, is_leaf=is_group)
    assert ta == tb, f"tree structures differ: {ta} vs {tb}"
    for x, y in zip(la, lb):
        if is_group(x):
            assert type(x) is type(y)
            assert_close(
                ref_matrix(type(x), x.data),
                ref_matrix(type(y), y.data),
                np.float64,
                f64=f64,
                err_msg=err_msg,
            )
        else:
            assert_close(x, y, np.float64, f64=f64, err_msg=err_msg)


# ------------------------------------------------------------------------------------
# retraction / rminus / zero_tangent / tangent_size / normalize_all
# ------------------------------------------------------------------------------------
def test_retract_is_right_multiplication_by_exp_and_addition():
    p = _params()
    d = _random_tangent(p)
    q = manifold.retract(p, d)
    for x, delta, y in zip(
        jax.tree.leaves(p, is_leaf=is_group),
        jax.tree.leaves(d, is_leaf=is_group),
        jax.tree.leaves(q, is_leaf=is_group),
    ):
        if is_group(x):
            assert type(y) is type(x) and y.shape == x.shape
            expected = ref_matrix(type(x), x.data) @ ref_exp_matrix(type(x), delta)
            assert_close(ref_matrix(type(y), y.data), expected, np.float64)
        else:
            assert_close(y, np.asarray(x) + delta, np.float64, f64=0.0)


def test_flat_tangent_layout_and_retraction():
    p = _params()
    d = _random_tangent(p)
    flat0, unravel = manifold.flat_tangent(p)
    flat_d, _ = ravel_pytree(d)
    # the flat layout: zeros of size tangent_size, unravel inverts ravel of a tangent pytree
    assert flat0.shape == (manifold.tangent_size(p),) and not np.any(np.asarray(flat0))
    _assert_trees_close(unravel(flat_d), d, f64=0.0)
    _assert_trees_close(manifold.retract(p, unravel(flat_d)), manifold.retract(p, d))
    # a flat retraction differentiates and jits: d/dε (p ⊕ ε) ⊖ p at 0 is the identity
    f = lambda e: ravel_pytree(manifold.rminus(manifold.retract(p, unravel(e)), p))[0]
    jac = jax.jit(jax.jacfwd(f))(flat0)
    assert_close(jac, np.eye(flat0.size), np.float64, f64=1e-12)


def test_retract_rminus_are_inverse():
    p = _params()
    d = _random_tangent(p)
    q = manifold.retract(p, d)
    # (p ⊕ δ) ⊖ p = δ
    back = manifold.rminus(q, p)
    assert jax.tree.structure(back) == jax.tree.structure(d)
    for x, y in zip(jax.tree.leaves(back), jax.tree.leaves(d)):
        assert_close(x, y, np.float64)
    # p ⊕ (q ⊖ p) = q for a second, unrelated point q with relative rotations below π
    q2 = manifold.retract(p, _random_tangent(p, seed=7, max_angle=2.8))
    _assert_trees_close(manifold.retract(p, manifold.rminus(q2, p)), q2)
    # p ⊕ 0 = p and p ⊖ p = 0
    _assert_trees_close(manifold.retract(p, manifold.zero_tangent(p)), p, f64=1e-15)
    for leaf in jax.tree.leaves(manifold.rminus(p, p)):
        assert_close(leaf, np.zeros_like(leaf), np.float64, f64=1e-15)


def test_retract_rminus_under_jit():
    p = _params()
    d = _random_tangent(p)
    q = fast_jit(manifold.retract)(p, d)
    _assert_trees_close(q, manifold.retract(p, d), f64=1e-12)
    back = fast_jit(manifold.rminus)(q, p)
    for x, y in zip(jax.tree.leaves(back), jax.tree.leaves(d)):
        assert_close(x, y, np.float64)


@pytest.mark.parametrize("dtype", [np.float32, np.float64], ids=["float32", "float64"])
def test_zero_tangent_and_tangent_size(dtype):
    p = _params(dtype=dtype)
    z = manifold.zero_tangent(p)
    expected_shapes = {
        "pose": (3, 6),
        "pair": ((3,), (2, 1)),
        "nested": {"v": (4,), "sim": (7,), "list": [(4,), (1, 3)]},
        "scalar": (),
    }
    shapes = jax.tree.map(jnp.shape, z)
    assert shapes == expected_shapes
    for leaf in jax.tree.leaves(z):
        assert leaf.dtype == dtype
        assert not np.any(np.asarray(leaf))
    assert manifold.tangent_size(p) == 18 + 3 + 2 + 4 + 7 + 4 + 3 + 1
    assert manifold.tangent_size(SE3.identity((5,))) == 30
    assert manifold.tangent_size(jnp.zeros((2, 3))) == 6


def test_normalize_all():
    p = _params()
    rng = np.random.default_rng(3)
    noisy = jax.tree.map(
        lambda x: (
            type(x)(np.asarray(x.data) + 1e-2 * rng.normal(size=x.data.shape)) if is_group(x) else x
        ),
        p,
        is_leaf=is_group,
    )
    out = manifold.normalize_all(noisy)
    pairs = zip(jax.tree.leaves(noisy, is_leaf=is_group), jax.tree.leaves(out, is_leaf=is_group))
    for x, y in pairs:
        if not is_group(x):
            assert y is x or np.array_equal(np.asarray(y), np.asarray(x))
            continue
        assert type(y) is type(x)
        cls = type(x)
        sl = QUAT_SLICE.get(cls, COSSIN_SLICE.get(cls))
        yd, xd = np.asarray(y.data), np.asarray(x.data)
        assert_close(np.linalg.norm(yd[..., sl], axis=-1), np.ones(x.shape), np.float64, f64=1e-14)
        expected = xd.copy()
        expected[..., sl] /= np.linalg.norm(xd[..., sl], axis=-1, keepdims=True)
        assert_close(yd, expected, np.float64, f64=1e-14)


# ------------------------------------------------------------------------------------
# tangent-space gradients and Jacobians vs finite differences through the retraction
# ------------------------------------------------------------------------------------
def _targets(seed=11):
    rng = np.random.default_rng(seed)
    return {
        "T": SE3(random_group_data(rng, SE3, (3,))),
        "R": SO3(random_group_data(rng, SO3, ())),
        "pts": rng.normal(size=(5, 3)),
    }


def _loss(params, tg):
    """A scalar touching every leaf (groups through log / act / matrix, arrays directly)."""
    pose, (rot, planar) = params["pose"], params["pair"]
    nested = params["nested"]
    val = jnp.sum((pose.inv() @ tg["T"]).log().data ** 2)
    val += jnp.sum((rot @ tg["pts"]) * tg["pts"][::-1]) + jnp.sum(planar.matrix() ** 3)
    val += jnp.sum(nested["sim"].act(tg["pts"]) ** 2) * nested["v"][0]
    val += jnp.sum(nested["v"] ** 2) + jnp.sum(nested["list"][0].log().data * nested["v"])
    val += jnp.sum(nested["list"][1].translation() ** 2) * params["scalar"]
    return val + jnp.sin(params["scalar"])


def _vector_fn(params, tg):
    """A pytree-valued function for Jacobians."""
    pose, (rot, _) = params["pose"], params["pair"]
    return {
        "a": (pose @ tg["pts"][:3]).reshape(-1),
        "b": (rot.inv() @ tg["R"]).log().data * params["scalar"],
        "c": params["nested"]["sim"].matrix()[:3, :3] + params["nested"]["v"][1],
    }


def _fd_tangent(fun, params, eps=1e-6):
    """Central differences of fun(params ⊕ δ) w.r.t. the flattened tangent δ: (*out, n).

    All 2n perturbed evaluations run in one vmapped, jitted call."""
    flat0, unravel = ravel_pytree(manifold.zero_tangent(params))
    n = flat0.size
    steps = np.concatenate([np.eye(n), -np.eye(n)]) * eps
    vals = fast_jit(jax.vmap(lambda e: fun(manifold.retract(params, unravel(e)))))(steps)
    return jax.tree.map(
        lambda v: np.moveaxis((np.asarray(v[:n]) - np.asarray(v[n:])) / (2 * eps), 0, -1), vals
    ), unravel


def test_grad_and_value_and_grad_match_finite_differences():
    p, tg = _params(), _targets()

    def loss2(q, pts):
        return _loss(q, {**tg, "pts": pts})

    @fast_jit
    def everything(p, tg):
        return {
            "grad": manifold.grad(_loss)(p, tg),
            "vg": manifold.value_and_grad(_loss)(p, tg),
            "aux": manifold.grad(lambda q, t: (_loss(q, t), 7.0), has_aux=True)(p, tg),
            "vg_aux": manifold.value_and_grad(lambda q, t: (_loss(q, t), 3.0), has_aux=True)(p, tg),
            "two": manifold.grad(loss2, argnums=(0, 1))(p, tg["pts"]),
            "loss": _loss(p, tg),
        }

    r = everything(p, tg)
    g = r["grad"]
    # tangent structure: group leaves become (*batch, tangent_dim) arrays
    assert jax.tree.structure(g) == jax.tree.structure(manifold.zero_tangent(p))
    fd, _ = _fd_tangent(lambda q: _loss(q, tg), p)
    flat_g, _ = ravel_pytree(g)
    assert_close(flat_g, fd, np.float64, f64=1e-6, err_msg="manifold.grad vs FD")

    val, g2 = r["vg"]
    assert_close(val, r["loss"], np.float64, f64=1e-14)
    assert_close(ravel_pytree(g2)[0], flat_g, np.float64, f64=1e-14)
    ga, aux = r["aux"]
    assert float(aux) == 7.0
    assert_close(ravel_pytree(ga)[0], flat_g, np.float64, f64=1e-14)
    (vv, aux2), _ = r["vg_aux"]
    assert float(aux2) == 3.0 and np.isclose(vv, val)

    # several argnums: the array argument is differentiated as usual
    g_p, g_pts = r["two"]
    assert_close(ravel_pytree(g_p)[0], flat_g, np.float64, f64=1e-12)
    steps = np.concatenate([np.eye(15), -np.eye(15)]).reshape(30, 5, 3) * 1e-6
    vals = np.asarray(fast_jit(jax.vmap(lambda e: loss2(p, tg["pts"] + e)))(steps))
    fd_pts = ((vals[:15] - vals[15:]) / 2e-6).reshape(5, 3)
    assert_close(g_pts, fd_pts, np.float64, f64=1e-6, err_msg="array argument gradient")


def test_grad_of_a_group_argument_alone():
    rng = np.random.default_rng(4)
    x = SE3(random_group_data(rng, SE3, ()))
    t = SE3(random_group_data(rng, SE3, ()))

    def f(x):
        return jnp.sum((x.inv() @ t).log().data ** 2)

    g = manifold.grad(f)(x)
    assert g.shape == (6,)
    fd, _ = _fd_tangent(f, x)
    assert_close(g, fd, np.float64, f64=1e-6)
    # closed form: d/dδ ||Log(Exp(−δ)·X⁻¹T)||² = −2 Jl⁻¹(ξ)ᵀ ξ with ξ = Log(X⁻¹T)
    xi = (x.inv() @ t).log()
    assert_close(g, -2 * np.asarray(xi.jl_inv()).T @ np.asarray(xi.data), np.float64, f64=1e-10)


@pytest.mark.parametrize("mode", ["fwd", "rev", "auto"])
def test_jacobian_modes_match_finite_differences(mode):
    p, tg = _params(), _targets()
    jac = fast_jit(manifold.jacobian(_vector_fn, mode=mode))(p, tg)
    fd, _ = _fd_tangent(lambda q: _vector_fn(q, tg), p)
    zero = manifold.zero_tangent(p)
    n_leaves = len(jax.tree.leaves(zero))
    for key in ("a", "b", "c"):
        out_shape = np.shape(_vector_fn(p, tg)[key])
        leaves = jax.tree.leaves(jac[key])
        assert len(leaves) == n_leaves
        for leaf, z in zip(leaves, jax.tree.leaves(zero)):
            assert leaf.shape == (*out_shape, *z.shape)
        # flatten the per-leaf Jacobians in ravel_pytree order and compare with FD
        flat = np.concatenate([np.asarray(leaf).reshape(*out_shape, -1) for leaf in leaves], -1)
        assert_close(flat, fd[key], np.float64, f64=1e-6, err_msg=f"{mode} {key}")


def test_jacobian_argnums_tuple_and_has_aux():
    p, tg = _params(), _targets()

    def f(q, s):
        out = _vector_fn(q, tg)
        return out["b"] * s, out["a"].sum()

    jac = manifold.jacobian(f, argnums=(0, 1), mode="rev", has_aux=True)
    (jq, js), aux = fast_jit(jac)(p, 2.0)
    assert np.isclose(aux, _vector_fn(p, tg)["a"].sum())
    assert_close(js, _vector_fn(p, tg)["b"], np.float64, f64=1e-12)
    fd, _ = _fd_tangent(lambda q: f(q, 2.0)[0], p)
    flat = np.concatenate([np.asarray(x).reshape(3, -1) for x in jax.tree.leaves(jq)], -1)
    assert_close(flat, fd, np.float64, f64=1e-6)


@pytest.mark.parametrize("mode", ["fwd", "rev"])
def test_jacobian_of_tuple_output_with_int_argnums(mode):
    x = SE3.exp(jnp.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6]))
    jac = manifold.jacobian(lambda x: (x.translation(), x.log().data), mode=mode)(x)
    assert isinstance(jac, tuple) and len(jac) == 2
    assert jac[0].shape == (3, 6) and jac[1].shape == (6, 6)
    # d t(X·Exp(δ))/dδ = [R, 0]; d Log(X·Exp(δ))/dδ = Jr⁻¹(Log X)
    r = ref_matrix(SE3, x.data)[:3, :3]
    assert_close(jac[0], np.concatenate([r, np.zeros((3, 3))], 1), np.float64, f64=1e-12)
    assert_close(jac[1], x.log().jr_inv(), np.float64, f64=1e-12)


def test_bad_arguments():
    with pytest.raises(ValueError, match=r"jacobian\(mode='sideways'\).*'fwd'"):
        manifold.jacobian(lambda x: x, mode="sideways")
    with pytest.raises(TypeError, match=r"optax_on_manifold.*GradientTransformation.*str"):
        manifold.optax_on_manifold("adam")


# ------------------------------------------------------------------------------------
# optax on manifold parameters: pose averaging
# ------------------------------------------------------------------------------------
N_POSES = 12


def _noisy_poses(cls, seed=0, sigma=0.3):
    rng = np.random.default_rng(seed)
    mean = cls(random_group_data(rng, cls, ()))
    noise = random_tangent(rng, cls, (N_POSES,), max_angle=sigma * 2)
    noise[..., :3] *= sigma if cls is SE3 else 1.0
    ts = cls(ref_matrix_to_data(cls, ref_matrix(cls, mean.data) @ ref_exp_matrix(cls, noise)))
    return mean, ts


def ref_matrix_to_data(cls, m):
    """Storage data from matrices (scipy), independent of from_matrix."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_matrix(m[..., :3, :3]).as_quat()
    return np.concatenate([m[..., :3, 3], rot], -1) if cls is SE3 else rot


def _np_log(cls, m):
    """Log of an SO3 (3×3) or SE3 (4×4) matrix in closed form (scipy's rotation vector and
    the inverse V-matrix): the same principal logarithm as scipy.linalg.logm, ~100x faster,
    independent of jaxpose. Checked against logm in test_np_log_matches_logm."""
    from scipy.spatial.transform import Rotation

    phi = Rotation.from_matrix(m[:3, :3]).as_rotvec()
    if cls is SO3:
        return phi
    th = np.linalg.norm(phi)
    w = ref_hat(SO3, phi)
    if th < 1e-8:
        v_inv = np.eye(3) - 0.5 * w + w @ w / 12.0
    else:
        c = (1 - th / 2 / np.tan(th / 2)) / th**2
        v_inv = np.eye(3) - 0.5 * w + c * (w @ w)
    return np.concatenate([v_inv @ m[:3, 3], phi])


@pytest.mark.parametrize("cls", [SO3, SE3], ids=lambda c: c.__name__)
def test_np_log_matches_logm(cls):
    _, ts = _noisy_poses(cls, seed=3)
    for m in ref_matrix(cls, ts.data):
        want = ref_vee(cls, np.real(scipy.linalg.logm(m)))
        np.testing.assert_allclose(_np_log(cls, m), want, rtol=0, atol=1e-10)


def _karcher_bi_invariant(cls, ts_m, x0_m, iters=100):
    """The brief's fixed point X ← X·Exp(mean_i Log(X⁻¹Ti)) with scipy expm/logm. For SO3
    (bi-invariant metric) its fixed point is the minimiser of Σ‖Log(X⁻¹Ti)‖²."""
    x = x0_m
    for _ in range(iters):
        step = np.mean([_np_log(cls, np.linalg.solve(x, t)) for t in ts_m], 0)
        x = x @ scipy.linalg.expm(ref_hat(cls, step))
        if np.linalg.norm(step) < 1e-14:
            break
    return x


def _loss_np(cls, x_m, ts_m):
    return sum(np.sum(_np_log(cls, np.linalg.solve(x_m, t)) ** 2) for t in ts_m)


def _karcher_exact(cls, ts_m, x0_m, iters=60):
    """Minimiser of Σ‖Log(X⁻¹Ti)‖² on SE3 (no bi-invariant metric, so the plain fixed point
    above is only an approximation): the same right-trivialised fixed-point iteration driven
    by the exact tangent gradient, taken by central differences of the scipy-logm loss."""
    x, d, eps = x0_m, cls.tangent_dim, 1e-6
    for _ in range(iters):
        g = np.array(
            [
                (
                    _loss_np(cls, x @ scipy.linalg.expm(ref_hat(cls, e)), ts_m)
                    - _loss_np(cls, x @ scipy.linalg.expm(ref_hat(cls, -e)), ts_m)
                )
                / (2 * eps)
                for e in np.eye(d) * eps
            ]
        )
        step = -g / (2 * len(ts_m))
        x = x @ scipy.linalg.expm(ref_hat(cls, step))
        if np.linalg.norm(step) < 1e-12:
            break
    return x


def _pose_loss(ts):
    def loss(params):
        x = params["X"]
        return jnp.sum((x.inv() @ ts).log().data ** 2)

    return loss


def _optimise(opt, params, loss, steps):
    mopt = manifold.optax_on_manifold(opt)

    @fast_jit
    def run(params):
        def body(carry, _):
            params, state = carry
            val, g = manifold.value_and_grad(loss)(params)
            updates, state = mopt.update(g, state, params)
            return (mopt.apply_updates(params, updates), state), val

        (params, _), vals = jax.lax.scan(body, (params, mopt.init(params)), None, length=steps)
        return params, vals

    return run(params)


@pytest.mark.parametrize("cls", [SO3, SE3], ids=lambda c: c.__name__)
def test_adam_on_manifold_finds_the_karcher_mean(cls):
    mean, ts = _noisy_poses(cls)
    ts_m = ref_matrix(cls, ts.data)
    start = cls(random_group_data(np.random.default_rng(9), cls, ()))
    if cls is SO3:
        ref = _karcher_bi_invariant(cls, ts_m, ref_matrix(cls, mean.data))
    else:
        ref = _karcher_exact(cls, ts_m, ref_matrix(cls, mean.data))
        # sanity of the reference: it is a stationary point of the loss (FD gradient ≈ 0)
        assert _loss_np(cls, ref, ts_m) <= _loss_np(cls, ref_matrix(cls, mean.data), ts_m)

    schedule = optax.exponential_decay(0.1, transition_steps=3000, decay_rate=1e-4)
    params, vals = _optimise(optax.adam(schedule), {"X": start}, _pose_loss(ts), 3000)
    x = params["X"]
    assert type(x) is cls and x.shape == ()
    vals = np.asarray(vals)
    assert np.all(np.isfinite(vals)) and vals[-1] < vals[0]
    err = _np_log(cls, np.linalg.solve(ref, ref_matrix(cls, x.data)))
    assert np.linalg.norm(err) < 1e-6, f"Adam optimum off the Karcher mean by {err}"
    # stored quaternion stays on the manifold
    q = np.asarray(x.data)[QUAT_SLICE[cls]]
    assert abs(np.linalg.norm(q) - 1) < 1e-9


@pytest.mark.parametrize("cls", [SO3, SE3], ids=lambda c: c.__name__)
def test_sgd_on_manifold_finds_the_karcher_mean(cls):
    mean, ts = _noisy_poses(cls, seed=1)
    ts_m = ref_matrix(cls, ts.data)
    start = cls(random_group_data(np.random.default_rng(2), cls, ()))
    ref = (_karcher_bi_invariant if cls is SO3 else _karcher_exact)(
        cls, ts_m, ref_matrix(cls, mean.data)
    )
    # lr = 1/(2N): on SO3 the SGD step is exactly the Karcher fixed-point step mean_i Log(X⁻¹Ti)
    params, vals = _optimise(optax.sgd(1.0 / (2 * N_POSES)), {"X": start}, _pose_loss(ts), 200)
    err = _np_log(cls, np.linalg.solve(ref, ref_matrix(cls, params["X"].data)))
    assert np.linalg.norm(err) < 1e-9, f"SGD optimum off the Karcher mean by {err}"
    assert np.all(np.diff(np.asarray(vals)) <= 1e-12), "SGD with lr = 1/(2N) should descend"


def test_optax_adapter_mixed_pytree_and_state():
    """Adam on a pytree mixing a group batch and an array: both converge to their targets."""
    rng = np.random.default_rng(5)
    targets = SO3(random_group_data(rng, SO3, (3,)))
    vec_target = rng.normal(size=4)

    def loss(p):
        return jnp.sum((p["R"].inv() @ targets).log().data ** 2) + jnp.sum(
            (p["v"] - vec_target) ** 2
        )

    params = {"R": SO3.identity((3,)), "v": jnp.zeros(4)}
    mopt = manifold.optax_on_manifold(optax.adam(0.05))
    state = mopt.init(params)
    # state is built on the tangent pytree (group leaves → (*batch, 3))
    mu = state[0].mu
    assert mu["R"].shape == (3, 3) and mu["v"].shape == (4,)
    schedule = optax.exponential_decay(0.05, transition_steps=1500, decay_rate=1e-3)
    params, vals = _optimise(optax.adam(schedule), params, loss, 1500)
    assert float(vals[-1]) < 1e-10
    err = (params["R"].inv() @ targets).log().data
    assert np.max(np.abs(np.asarray(err))) < 1e-5
    assert_close(params["v"], vec_target, np.float64, f64=1e-5)
    assert isinstance(params["R"], LieGroup)
