"""Every public Lie-group op under jax.jit, jax.vmap, jax.grad, jax.jacfwd, jax.jacrev and
jax.hessian (nested), for every group.

Each op is written twice, as a method and as the module-level function (``jaxpose.lie`` /
``jaxpose`` / ``jaxpose.lie.manifold``), as a function of plain float64 arrays (group
arguments are their raw storage, so derivatives are taken in the ambient coordinates). The
references are the eager results: jit and vmap must reproduce eager values, and every
derivative is compared with central finite differences of eager evaluations (and jacfwd with
jacrev). Group and algebra objects also cross jit / vmap / scan / cond boundaries as pytrees.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose as jp
from jaxpose.lie import SE2, SE3, SO3, LieAlgebra, LieGroup, manifold

from .conftest import GROUPS, GROUPS_3D, assert_close, fast_jit, random_tangent

KEY = jax.random.key(42)


@dataclasses.dataclass(frozen=True)
class Op:
    name: str
    method: Callable[..., object]
    functional: Callable[..., object]
    args: Callable[[np.random.Generator], list[np.ndarray]]


def _element(rng: np.random.Generator, cls: type[LieGroup], shape=(), max_angle=2.0):
    a = random_tangent(rng, cls, shape, max_angle=max_angle)
    return np.asarray(cls.exp(a).data, np.float64)


def _ops(cls: type[LieGroup]) -> list[Op]:
    alg = cls.algebra
    n = cls.point_dim

    def el(rng):
        return _element(rng, cls)

    def tan(rng, max_angle=1.5):
        return random_tangent(rng, cls, (), max_angle=max_angle)

    def pair(rng):  # y = x·Exp(b), relative rotation below π
        x = el(rng)
        return [x, np.asarray((cls(x) @ cls.exp(tan(rng, 2.0))).data)]

    ops = [
        Op("exp", lambda a: alg(a).exp(), lambda a: jp.exp(alg(a)), lambda r: [tan(r, 2.5)]),
        Op("log", lambda x: cls(x).log(), lambda x: jp.log(cls(x)), lambda r: [el(r)]),
        Op("inv", lambda x: cls(x).inv(), lambda x: jp.inv(cls(x)), lambda r: [el(r)]),
        Op(
            "compose",
            lambda x, y: cls(x) @ cls(y),
            lambda x, y: jp.compose(cls(x), cls(y)),
            lambda r: [el(r), el(r)],
        ),
        Op(
            "act",
            lambda x, p: cls(x) @ p,
            lambda x, p: jp.act(cls(x), p),
            lambda r: [el(r), r.normal(size=n)],
        ),
        Op(
            "act_homogeneous",
            lambda x, p: cls(x).act(p),
            lambda x, p: jp.lie.act(cls(x), p),
            lambda r: [el(r), r.normal(size=n + 1)],
        ),
        Op(
            "adj",
            lambda x, a: cls(x).adj(alg(a)),
            lambda x, a: jp.adj(cls(x), a),
            lambda r: [el(r), tan(r)],
        ),
        Op(
            "adjT",
            lambda x, a: cls(x).adjT(alg(a)),
            lambda x, a: jp.adjT(cls(x), a),
            lambda r: [el(r), tan(r)],
        ),
        Op(
            "jinvp",
            lambda x, a: cls(x).jinvp(alg(a)),
            lambda x, a: jp.jinvp(cls(x), a),
            lambda r: [el(r), tan(r)],
        ),
        Op("jr", lambda a: alg(a).jr(), lambda a: jp.jr(alg(a)), lambda r: [tan(r, 2.5)]),
        Op("jl", lambda a: alg(a).jl(), lambda a: jp.jl(alg(a)), lambda r: [tan(r, 2.5)]),
        Op(
            "jr_inv",
            lambda a: alg(a).jr_inv(),
            lambda a: jp.jr_inv(alg(a)),
            lambda r: [tan(r, 2.5)],
        ),
        Op(
            "jl_inv",
            lambda a: alg(a).jl_inv(),
            lambda a: jp.jl_inv(alg(a)),
            lambda r: [tan(r, 2.5)],
        ),
        Op("hat", lambda a: alg(a).hat(), lambda a: jp.lie.hat(alg(a)), lambda r: [tan(r)]),
        Op("matrix", lambda x: cls(x).matrix(), lambda x: jp.matrix(cls(x)), lambda r: [el(r)]),
        Op(
            "algebra_matrix",
            lambda a: alg(a).matrix(),
            lambda a: jp.matrix(alg(a)),
            lambda r: [tan(r)],
        ),
        Op(
            "from_matrix",
            lambda mm: cls.from_matrix(mm, check=False),
            lambda mm: jp.from_matrix(cls, mm, check=False),
            lambda r: [np.asarray(cls(el(r)).matrix())],
        ),
        Op(
            "from_matrix_checked",
            lambda mm: cls.from_matrix(mm),
            lambda mm: jp.lie.from_matrix(cls, mm, check=True),
            lambda r: [np.asarray(cls(el(r)).matrix())],
        ),
        Op(
            "translation",
            lambda x: cls(x).translation(),
            lambda x: jp.translation(cls(x)),
            lambda r: [el(r)],
        ),
        Op(
            "rotation",
            lambda x: cls(x).rotation(),
            lambda x: jp.rotation(cls(x)),
            lambda r: [el(r)],
        ),
        Op("scale", lambda x: cls(x).scale(), lambda x: jp.scale(cls(x)), lambda r: [el(r)]),
        Op(
            "identity",
            lambda x: cls.identity((), x.dtype) @ cls(x),
            lambda x: jp.compose(jp.identity(cls, (), x.dtype), cls(x)),
            lambda r: [el(r)],
        ),
        Op(
            "random",
            lambda s: cls.random(KEY, (2,), s),
            lambda s: jp.random(cls, KEY, (2,), s),
            lambda r: [np.asarray(r.uniform(0.3, 0.8))],
        ),
        Op(
            "normalize",
            lambda x: cls(x).normalize(),
            lambda x: jp.normalize(cls(x)),
            lambda r: [el(r) + 0.05 * r.normal(size=cls.storage_dim)],
        ),
        Op(
            "interpolate",
            lambda x, y, t: cls(x).interpolate(cls(y), t),
            lambda x, y, t: jp.interpolate(cls(x), cls(y), t),
            lambda r: [*pair(r), np.asarray(r.uniform(0.1, 0.9))],
        ),
        Op(
            "cumprod_left",
            lambda xs: cls(xs).cumprod(0),
            lambda xs: jp.cumprod(cls(xs), axis=-1, left=True),
            lambda r: [_element(r, cls, (4,))],
        ),
        Op(
            "cumprod_right",
            lambda xs: cls(xs).cumprod(0, left=False),
            lambda xs: jp.cumprod(cls(xs), 0, False),
            lambda r: [_element(r, cls, (4,))],
        ),
        Op(
            "retract",
            lambda x, a: cls(x).retract(a),
            lambda x, a: manifold.retract(cls(x), a),
            lambda r: [el(r), tan(r)],
        ),
        Op(
            "rminus",
            lambda x, y: cls(y).rminus(cls(x)),
            lambda x, y: manifold.rminus(cls(y), cls(x)),
            pair,
        ),
    ]
    if cls in GROUPS_3D:
        ops.append(
            Op("euler", lambda x: cls(x).euler(), lambda x: jp.euler(cls(x)), lambda r: [el(r)])
        )
    if cls is SO3:
        ops.append(
            Op(
                "from_euler",
                lambda e: SO3.from_euler(e),
                lambda e: jp.from_euler(e),
                lambda r: [r.uniform([-3, -1.4, -3], [3, 1.4, 3])],
            )
        )
    return ops


# Compilation dominates the cost of this file, so derivatives are spread over two tiers
# (autodiff is compositional, so the composite ops inherit correct derivatives from their
# parts; test_properties and test_numerics also check Jacobians of every group):
# * default: every op of SO3, SE3 and SE2 under jit and vmap; SE3 (the most composite
#   group) under grad / jacfwd / jacrev for DERIV_OPS and the Hessian for HESSIAN_OPS;
# * slow (``-m slow``): every op of every group under jit and vmap, every op of SE3 under
#   every transform, and for the other groups grad / jacfwd / jacrev for DERIV_OPS and
#   the Hessian for HESSIAN_OPS.
FULL_GROUP = SE3
DERIV_OPS = {
    "exp",
    "log",
    "inv",
    "compose",
    "act",
    "adj",
    "jinvp",
    "jr",
    "jl_inv",
    "from_matrix",
    "normalize",
    "interpolate",
    "cumprod_left",
    "random",
    "rminus",
    "euler",
    "from_euler",
}
HESSIAN_OPS = {"exp", "log", "compose", "act", "jr", "interpolate", "euler", "from_euler"}
# from_matrix(check=True) raises at the off-manifold points that finite differences visit
NO_DERIV = {"from_matrix_checked"}


def _kinds(cls, name, full=True):
    kinds = {"jit", "vmap"}
    if name in NO_DERIV:
        return kinds
    if not full:
        if cls is FULL_GROUP and name in DERIV_OPS:
            kinds |= {"grad", "jac"}
        if cls is FULL_GROUP and name in HESSIAN_OPS:
            kinds |= {"hessian"}
        return kinds
    if cls is FULL_GROUP or name in DERIV_OPS:
        kinds |= {"grad", "jac"}
    if cls is FULL_GROUP or name in HESSIAN_OPS:
        kinds |= {"hessian"}
    return kinds


OPS = {(cls, op.name): op for cls in GROUPS for op in _ops(cls)}


# groups whose ops run under jit / vmap in the default tier (the others, whose ops the
# property tests also run jitted, only in the slow tier)
DEFAULT_GROUPS = (SO3, SE3, SE2)


def _cases(kind):
    """(cls, name, full) parameters: in the default tier when ``kind`` is among the
    default kinds of the op, else in the slow tier (computed with the full bundle)."""
    out = []
    for cls, name in OPS:
        if kind not in _kinds(cls, name):
            continue
        pid = f"{cls.__name__}-{name}"
        if cls in DEFAULT_GROUPS and kind in _kinds(cls, name, full=False):
            out.append(pytest.param(cls, name, False, id=pid))
        else:
            out.append(pytest.param(cls, name, True, id=pid, marks=pytest.mark.slow))
    return out


def _raw(out: object) -> jax.Array:
    """Flattened array of an op output (group / algebra elements give their data)."""
    if isinstance(out, (LieGroup, LieAlgebra)):
        out = out.data
    return jnp.ravel(out)


def _args(op: Op, seed: int = 0) -> list[np.ndarray]:
    return [np.asarray(a, np.float64) for a in op.args(np.random.default_rng(seed))]


def _packed(op: Op, args: list[np.ndarray]):
    """(F, z0): F(z) = raw output as a function of all arguments packed into one vector."""
    shapes = [a.shape for a in args]
    sizes = [int(np.prod(s)) for s in shapes]

    def unpack(z):
        out, i = [], 0
        for s, k in zip(shapes, sizes):
            out.append(z[i : i + k].reshape(s))
            i += k
        return out

    def F(z):
        return _raw(op.functional(*unpack(z)))

    return F, np.concatenate([a.ravel() for a in args])


EPS = 1e-6


def _fd_points(z: np.ndarray) -> np.ndarray:
    e = np.eye(z.size) * EPS
    return np.concatenate([z + e, z - e], 0)


def _fd_from(values: np.ndarray) -> np.ndarray:
    """Central differences (*out, n) from f at _fd_points (2n, *out)."""
    values = np.asarray(values, np.float64)
    n = values.shape[0] // 2
    return np.moveaxis((values[:n] - values[n:]) / (2 * EPS), 0, -1)


@functools.cache
def _results(cls, name, full=False):
    """Everything a test needs for one op, transformed results computed in one compilation
    (``full``: every transform of the slow tier)."""
    op = OPS[cls, name]
    kinds = _kinds(cls, name, full)
    args = _args(op)
    rows = [_args(op, seed) for seed in range(3)]
    batched = [np.stack(col) for col in zip(*rows)]
    F, z = _packed(op, args)
    w = np.random.default_rng(1).normal(size=np.asarray(F(z)).size)

    def g(z):
        return jnp.sum(w * F(z))

    def bundle(args, batched, z, zfd):
        out = {"jit": op.functional(*args), "vmap": jax.vmap(op.method)(*batched)}
        if "grad" in kinds:
            out["grad"] = jax.grad(g)(z)
            out["fd_values"] = jax.vmap(F)(zfd)
        if "jac" in kinds:
            out["jacfwd"] = jax.jacfwd(F)(z)
            out["jacrev"] = jax.jacrev(F)(z)
        if "hessian" in kinds:
            out["hessian"] = jax.hessian(g)(z)
            out["fd_grads"] = jax.vmap(jax.grad(g))(zfd)
        return out

    res = fast_jit(bundle)(args, batched, z, _fd_points(z))
    res["eager"] = op.functional(*args)
    res["method"] = op.method(*args)
    res["loop"] = [op.method(*r) for r in rows]
    res["w"] = w
    return res


# ------------------------------------------------------------------------------------
# values: method == functional, jit == eager, vmap == loop
# ------------------------------------------------------------------------------------
@pytest.mark.parametrize("cls,name,full", _cases("jit"))
def test_method_equals_functional(cls, name, full):
    r = _results(cls, name, full)
    a, b = r["method"], r["eager"]
    assert type(a) is type(b)
    np.testing.assert_allclose(np.asarray(_raw(a)), np.asarray(_raw(b)), rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize("cls,name,full", _cases("jit"))
def test_jit_equals_eager(cls, name, full):
    r = _results(cls, name, full)
    assert type(r["jit"]) is type(r["eager"]), "group / algebra type lost through jit"
    assert_close(_raw(r["jit"]), _raw(r["eager"]), np.float64, f64=1e-12)


@pytest.mark.parametrize("cls,name,full", _cases("vmap"))
def test_vmap_equals_loop(cls, name, full):
    r = _results(cls, name, full)
    out, loop = r["vmap"], r["loop"]
    assert type(out) is type(loop[0]), "group / algebra type lost through vmap"
    if isinstance(out, (LieGroup, LieAlgebra)):
        assert out.shape == (3, *loop[0].shape)
    for i, ref in enumerate(loop):
        assert_close(_raw(out[i]), _raw(ref), np.float64, f64=1e-12, err_msg=f"row {i}")


# ------------------------------------------------------------------------------------
# derivatives (float64) against central finite differences
# ------------------------------------------------------------------------------------
@pytest.mark.parametrize("cls,name,full", _cases("grad"))
def test_grad_matches_finite_differences(cls, name, full):
    r = _results(cls, name, full)
    gr = np.asarray(r["grad"])
    assert np.all(np.isfinite(gr))
    fd = _fd_from(np.asarray(r["fd_values"]) @ r["w"])
    assert_close(gr, fd, np.float64, f64=1e-6, err_msg="grad of Σ w·f vs finite differences")


@pytest.mark.parametrize("cls,name,full", _cases("jac"))
def test_jacfwd_jacrev_match_finite_differences(cls, name, full):
    r = _results(cls, name, full)
    jf, jr = np.asarray(r["jacfwd"]), np.asarray(r["jacrev"])
    assert jf.shape == jr.shape == (r["w"].size, r["grad"].size)
    assert_close(jf, jr, np.float64, f64=1e-12, err_msg="jacfwd vs jacrev")
    assert_close(jf, _fd_from(r["fd_values"]), np.float64, f64=1e-6, err_msg="jacfwd vs FD")
    assert_close(jf.T @ r["w"], r["grad"], np.float64, f64=1e-12, err_msg="Jᵀw = grad")


@pytest.mark.parametrize("cls,name,full", _cases("hessian"))
def test_hessian_matches_finite_differences_of_grad(cls, name, full):
    r = _results(cls, name, full)
    h = np.asarray(r["hessian"])
    n = r["grad"].size
    assert h.shape == (n, n) and np.all(np.isfinite(h))
    assert_close(h, h.T, np.float64, f64=1e-10, err_msg="Hessian is symmetric")
    assert_close(h, _fd_from(r["fd_grads"]), np.float64, f64=1e-6, err_msg="vs FD of grad")


# ------------------------------------------------------------------------------------
# the derivative of a jitted function (grad outside jit): another partial-evaluation path
# ------------------------------------------------------------------------------------
def _vmapped_log(cls: type[LieGroup]) -> Callable[[jax.Array], jax.Array]:
    def one(d: jax.Array) -> jax.Array:
        a = cls(d).log()
        return jnp.concatenate([a.data, a.jr().ravel()])

    return lambda d: jnp.sum(jax.vmap(one)(d) ** 2)


@pytest.mark.parametrize("cls", GROUPS, ids=lambda g: g.__name__)
def test_grad_of_a_jitted_vmapped_function_equals_the_jitted_grad(cls):
    """``jax.grad(jax.jit(f))`` with the ops under vmap. jax 0.10 failed to transpose Log
    there (SO3's jr, SE3/Sim3/RxSO3's log: "Sum of sizes 3 must be equal to dimension 1")
    while Log's value and derivative formulas laid out their batch axis differently."""
    f = _vmapped_log(cls)
    x = jnp.asarray(_element(np.random.default_rng(11), cls, (4,)))
    outside = jax.grad(lambda d: jax.jit(f)(d))(x)
    assert np.all(np.isfinite(np.asarray(outside)))
    assert_close(outside, fast_jit(jax.grad(f))(x), np.float64, f64=1e-12)


def test_hessian_of_a_jitted_vmapped_function_equals_the_jitted_hessian():
    f = _vmapped_log(SE3)
    x = jnp.asarray(_element(np.random.default_rng(12), SE3, (2,)))
    outside = jax.hessian(lambda d: jax.jit(f)(d))(x)
    assert np.all(np.isfinite(np.asarray(outside)))
    assert_close(outside, fast_jit(jax.hessian(f))(x), np.float64, f64=1e-10)


# ------------------------------------------------------------------------------------
# group objects as pytrees through jit / vmap / scan / cond
# ------------------------------------------------------------------------------------
@pytest.mark.parametrize("cls", GROUPS, ids=lambda g: g.__name__)
def test_groups_are_pytrees_through_transforms(cls):
    rng = np.random.default_rng(5)
    xs = cls(_element(rng, cls, (4,)))
    a = cls.algebra(random_tangent(rng, cls, (4,), max_angle=1.0))
    leaves, treedef = jax.tree.flatten(xs)
    assert len(leaves) == 1 and leaves[0] is xs.data
    assert type(jax.tree.unflatten(treedef, leaves)) is cls

    # jit: groups and algebras in and out
    @fast_jit
    def step(x, t):
        return x @ t.exp(), (x @ t.exp()).log()

    y, ly = step(xs, a)
    assert type(y) is cls and type(ly) is cls.algebra and y.shape == (4,)
    y_e, ly_e = xs @ a.exp(), (xs @ a.exp()).log()
    assert_close(y.data, y_e.data, np.float64, f64=1e-12)
    assert_close(ly.data, ly_e.data, np.float64, f64=1e-12)

    # vmap over group objects, with an unbatched (in_axes=None) group argument
    x0 = xs[0]
    out = jax.vmap(lambda x, t, c: c @ x.retract(t), in_axes=(0, 0, None))(xs, a, x0)
    assert type(out) is cls and out.shape == (4,)
    assert_close(out.data, (x0 @ xs.retract(a)).data, np.float64, f64=1e-12)
    # vmap returning a group built inside
    made = jax.vmap(lambda t: cls.exp(t))(a.data)
    assert type(made) is cls and made.shape == (4,)

    # lax.scan with a group carry reproduces cumprod(left=False)
    def body(carry, x):
        nxt = carry @ x
        return nxt, nxt

    last, stacked = jax.lax.scan(body, cls.identity(), xs)
    assert type(last) is cls and type(stacked) is cls and stacked.shape == (4,)
    assert_close(stacked.data, xs.cumprod(0, left=False).data, np.float64, f64=1e-12)

    # lax.cond / tree.map with groups
    pick = fast_jit(lambda flag, x, y: jax.lax.cond(flag, lambda: x, lambda: y.inv()))
    assert_close(pick(True, xs, xs).data, xs.data, np.float64, f64=0.0)
    assert_close(pick(False, xs, xs).data, xs.inv().data, np.float64, f64=1e-14)  # FMA
    doubled = jax.tree.map(lambda leaf: leaf * 2.0, xs)
    assert type(doubled) is cls
    np.testing.assert_array_equal(np.asarray(doubled.data), 2.0 * np.asarray(xs.data))


@pytest.mark.parametrize("cls", GROUPS, ids=lambda g: g.__name__)
def test_identity_and_random_under_jit_and_vmap(cls):
    ident = fast_jit(lambda: jp.identity(cls, (2, 3), jnp.float32))()
    assert type(ident) is cls and ident.shape == (2, 3) and ident.dtype == jnp.float32
    np.testing.assert_array_equal(
        np.asarray(ident.data), np.asarray(cls.identity((2, 3), np.float32).data)
    )
    keys = jax.random.split(KEY, 3)
    batch = jax.vmap(lambda k: cls.random(k, (), 0.7))(keys)
    assert type(batch) is cls and batch.shape == (3,)
    for i in range(3):
        assert_close(batch.data[i], cls.random(keys[i], (), 0.7).data, np.float64, f64=1e-12)
    jitted = fast_jit(lambda k: jp.random(cls, k, (5,), 0.3))(KEY)
    assert_close(jitted.data, cls.random(KEY, (5,), 0.3).data, np.float64, f64=1e-12)


@pytest.mark.parametrize("scale", [1e-200, 1e200])
def test_normalize_derivatives_at_extreme_scales(scale):
    """normalize divides by m = max |qᵢ| first; its derivatives went through 1/m too and
    were NaN below ×1e-160 (m² underflows). The projection does not depend on the scale,
    so d normalize(c·q)/dq = d normalize(q)/dq / c exactly (degenerate-input audit)."""
    from jaxpose.lie import SO2

    for cls, x in ((SO3, jnp.array([0.1, -0.3, 0.2, 0.9])), (SO2, jnp.array([0.6, 0.7]))):
        f = jax.jit(lambda q, cls=cls: cls(q).normalize().data)
        ref = np.asarray(jax.jacfwd(f)(x)) / scale
        for jac in (jax.jacfwd(f)(x * scale), jax.jacrev(f)(x * scale)):
            np.testing.assert_allclose(np.asarray(jac), ref, rtol=1e-12, atol=0)
