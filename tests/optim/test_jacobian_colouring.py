"""Structural Jacobian sparsity, column colouring and the coloured LM path.

References are independent of the code under test: ``jax.jacfwd`` of the residual in the
tangent chart (the dense path's definition of the Jacobian), hand-written patterns, and
the dense solver's answers.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp
from jax.flatten_util import ravel_pytree

import jaxpose.optim as jo
from jaxpose.lie import SE3, manifold
from jaxpose.optim._colouring import BlockHessian, SparseJacobian, greedy_colouring
from jaxpose.optim._sparsity import jacobian_pattern

_MAX_POSES = 12
_exp = jax.jit(SE3.exp)


def _poses(batch: int, seed: int) -> SE3:
    """``batch`` ≤ 12 poses from seeded normal tangents. One compiled SE3.exp at a fixed batch
    size serves every test (eager exp compiles each primitive anew per batch size)."""
    tangents = np.random.default_rng(seed).normal(size=(batch, 6))
    padded = np.concatenate([tangents, np.zeros((_MAX_POSES - batch, 6))])
    return SE3(jnp.asarray(np.asarray(_exp(jnp.asarray(padded)).data)[:batch]))


def invnet(x: SE3, a: SE3) -> jax.Array:
    """PyPose's pose inversion: one 6-d residual per pose (block-diagonal Jacobian)."""
    return (x @ a).log().data


def banded(x: jax.Array, c: jax.Array) -> jax.Array:
    """Discrete second difference plus a nonlinearity: tridiagonal Jacobian (blocks of
    dimension 1: a residual of shape (m,) would be one block of dimension m)."""
    inner = x[:-2] - 2.0 * x[1:-1] + x[2:] + jnp.sin(x[1:-1]) * c
    return jnp.concatenate([inner, x[:1] - 1.0, x[-1:] + 1.0])[:, None]


def dense_res(x: jax.Array, a: jax.Array) -> jax.Array:
    return jnp.tanh(a @ x) - 0.1 * x


def mixed(p: dict, a: SE3) -> dict:
    """Pytree params (SE3 batch + array) and a pytree residual; v couples to its pose."""
    rot = (p["pose"] @ a).log().data + jnp.concatenate(
        [p["v"], jnp.zeros_like(p["v"])], -1)
    return {"rot": rot, "prior": (p["v"] - 0.5)[:, :, None]}


def trap(x: jax.Array, _: object) -> jax.Array:
    """Structurally nonzero entries that vanish at the test point: x_{i+1} = 0 makes
    ∂(x_i x_{i+1})/∂x_i = 0, and a ``where`` picks one of two inputs by value."""
    prod = x[:-2] * x[1:-1]
    pick = jnp.where(x[:-2] > 0, x[1:-1], x[2:])
    return jnp.stack([prod, pick], -1)


def _dense_jac(problem: jo.Problem, params, args):
    return jo.Problem(problem.residual_fn, jacobian="fwd").linearize(params, args).jac


def _coloured(problem_fn, params, args, **kw):
    prob = jo.Problem(problem_fn, jacobian="sparse", **kw)
    return prob, prob.linearize_structured(params, args)


# ----------------------------------------------------------------------------------
# pattern and colouring
# ----------------------------------------------------------------------------------
def test_invnet_pattern_is_block_diagonal_and_needs_six_colours():
    x, a = _poses(7, 0), _poses(7, 1)
    prob, lin = _coloured(invnet, x, a)
    pat = lin.jac.pattern
    assert pat.num_colours == 6
    assert len(pat.groups) == 1 and pat.groups[0].shape == (7, 6)
    # hand-written: pose i's 6 tangent columns, in its 6 residual rows only
    expected = np.kron(np.eye(7, dtype=bool), np.ones((6, 6), bool))
    dense = np.asarray(lin.jac.dense()) != 0
    assert not np.any(dense & ~expected)
    np.testing.assert_array_equal(np.asarray(lin.jac.dense()), _dense_jac(prob, x, a))


def test_banded_pattern_three_colours_and_exact_values():
    x = jnp.asarray(np.random.default_rng(3).normal(size=40))
    c = jnp.asarray(0.7)
    prob, lin = _coloured(banded, x, c)
    assert lin.jac.pattern.num_colours == 3
    assert lin.jac.pattern.groups is None  # one connected component: dense H
    np.testing.assert_array_equal(np.asarray(lin.jac.dense()), _dense_jac(prob, x, c))


def test_dense_pattern_needs_every_colour_and_matches_jacfwd():
    rng = np.random.default_rng(4)
    x, a = jnp.asarray(rng.normal(size=12)), jnp.asarray(rng.normal(size=(12, 12)))
    prob, lin = _coloured(dense_res, x, a)
    assert lin.jac.pattern.num_colours == 12
    np.testing.assert_array_equal(np.asarray(lin.jac.dense()), _dense_jac(prob, x, a))


def test_mixed_pytree_params_and_residual():
    p = {"pose": _poses(5, 5), "v": jnp.asarray(np.random.default_rng(6).normal(size=(5, 3)))}
    a = _poses(5, 7)
    prob, lin = _coloured(mixed, p, a)
    # columns: 30 pose + 15 v; a "rot" block touches 6 + 3 columns, a "prior" row one
    assert lin.jac.pattern.num_colours == 9
    np.testing.assert_array_equal(np.asarray(lin.jac.dense()), _dense_jac(prob, p, a))


def test_trap_structural_zero_at_the_point_is_kept():
    # x_{i+1} = 0 for even i: the product's ∂/∂x_i vanishes there numerically
    x = jnp.asarray([1.0, 0.0, -2.0, 0.0, 3.0, 0.0, -1.0, 0.0, 2.0, 0.5])
    flat = lambda e: trap(e, None).reshape(-1)  # noqa: E731
    _, pat = jacobian_pattern(flat, x)
    n = x.size
    expected = np.zeros((2 * (n - 2), n), bool)
    for i in range(n - 2):
        expected[2 * i, [i, i + 1]] = True  # x_i x_{i+1}
        # where(x_i > 0, x_{i+1}, x_{i+2}): both branches count, the predicate's x_i not
        expected[2 * i + 1, [i + 1, i + 2]] = True
    np.testing.assert_array_equal(pat.toarray(), expected)
    # numerically, jacfwd at x misses entries the pattern keeps ...
    jd = np.asarray(jax.jacfwd(flat)(x)) != 0
    assert np.sum(jd) < np.sum(expected)
    # ... and the coloured Jacobian is exact here and where the branches flip
    prob = jo.Problem(trap, jacobian="sparse")
    for point in (x, -x + 0.3, jnp.linspace(-1.0, 1.0, n)):
        got = prob.linearize(point, None).jac
        np.testing.assert_array_equal(np.asarray(got), _dense_jac(prob, point, None))


def test_optimization_barriers_keep_the_exact_pattern():
    """The Lie core materialises exp/log results through optimization barriers; the
    analysis sees through them (an unmodelled primitive would make the pattern dense)."""
    x = jnp.linspace(0.5, 2.0, 12)
    f = lambda x: jax.lax.optimization_barrier((x * 2.0, jnp.sin(x)))[0] * x
    _, pat = jacobian_pattern(f, x)
    np.testing.assert_array_equal(pat.toarray(), np.eye(12, dtype=bool))
    y = jnp.asarray(np.random.default_rng(3).normal(size=(5, 3)))
    _, pat = jacobian_pattern(lambda v: jax.vmap(lambda r: SE3.exp(
        jnp.concatenate([r, r])).log().data)(v.reshape(5, 3)).reshape(-1), y.reshape(-1))
    expected = np.kron(np.eye(5, dtype=bool), np.ones((6, 3), bool))
    assert not np.any(pat.toarray() & ~expected)  # one pose's outputs, its own inputs


def _roll_scan(x):  # x after three cyclic shifts: J is a permutation
    return jax.lax.scan(lambda c, _: (jnp.roll(c, 1), None), x, None, length=3)[0]


def _scan_over_slices(x):  # a running sum of x[::2] and the doubled x[1::2]
    c, ys = jax.lax.scan(lambda c, xi: (c + xi[0], xi[1] * 2.0), 0.0, x.reshape(3, 2))
    return jnp.concatenate([c[None], ys])


@pytest.mark.parametrize("f", [
    _roll_scan,
    lambda x: jax.lax.fori_loop(0, 3, lambda i, c: jnp.roll(c, 1), x),
    _scan_over_slices,
    lambda x: jax.lax.map(lambda r: r[::-1] * r, x.reshape(3, 2)).reshape(-1),
], ids=["scan-carry", "fori_loop", "scan-slices", "lax.map"])
def test_loops_never_miss_an_entry_of_the_pattern(f):
    """scan's body was analysed as a call of the whole operands: a carry rolled three
    times kept one roll's pattern and per-step slices the whole array's rows, so entries
    were missing (the sparse Jacobian was a wrong permutation, silently). Loops now get
    the conservative answer."""
    x = jnp.asarray(np.random.default_rng(5).normal(size=6))
    _, pat = jacobian_pattern(f, x)
    jac = np.asarray(jax.jacfwd(f)(x))
    assert not np.any((jac != 0) & ~pat.toarray())


def test_scan_residual_solves_on_the_sparse_path():
    target = jnp.arange(6.0)
    res = lambda x, _: (_roll_scan(x) - target)[:, None]  # noqa: E731
    sol = jo.least_squares(res, jnp.zeros(6), jacobian="sparse", max_steps=20)
    np.testing.assert_allclose(sol.params, np.roll(target, -3), atol=1e-10)  # was wrong


def test_constant_indices_folded_as_xla_computes_them():
    """Index arrays computed from constants are folded on the host. A float out of an
    integer type's range was converted by NumPy (−1.5 → uint8 255, 300.0 → 44), where XLA
    saturates (0, 255): the pattern named the wrong column. And a uint8 dynamic-slice
    start of 200 is clamped by eager JAX (→ 21) but read as −56 (→ 0) by XLA's constant
    folding under jit: no one answer, so its pattern is the conservative one. Both gave
    wrong least-squares solutions on the sparse path (sparsity fuzz)."""
    coords = np.array([-1.5, 3.2, 7.9, 300.0])

    def saturated(x, _):
        idx = jnp.minimum(jnp.asarray(coords).astype(jnp.uint8).astype(jnp.int32), 11)
        r = jnp.concatenate([x[idx] ** 2 - jnp.array([4.0, 9.0, 1.0, 16.0]), 0.1 * (x - 1)])
        return r[:, None]

    def unsigned_start(x, _):
        r = jax.lax.dynamic_slice(x, (jnp.uint8(200),), (3,)) ** 2 - 4.0
        return jnp.concatenate([r, 0.1 * (x - 1.0)])[:, None]

    for res, n in ((saturated, 12), (unsigned_start, 24)):
        x0 = jnp.full(n, 0.5)
        f = lambda x, res=res: res(x, None).ravel()  # noqa: E731
        _, pat = jacobian_pattern(f, x0)
        jac = np.asarray(jax.jit(jax.jacfwd(f))(x0))  # what least_squares' program computes
        assert not np.any((jac != 0) & ~pat.toarray())
        sparse = jo.least_squares(res, x0, jacobian="sparse")
        dense = jo.least_squares(res, x0, jacobian="fwd")
        np.testing.assert_allclose(sparse.params, dense.params, atol=1e-10)


def test_traced_indices_fall_back_to_a_conservative_pattern():
    def res(x, args):
        idx, y = args
        return (x[idx] * x[idx] - y)[:, None]

    x = jnp.linspace(0.5, 2.0, 20)
    idx = jnp.asarray(np.random.default_rng(8).integers(0, 20, 30))
    y = jnp.ones(30)
    prob = jo.Problem(res, jacobian="sparse")
    got = jax.jit(lambda x, idx: prob.linearize(x, (idx, y)).jac)(x, idx)
    np.testing.assert_array_equal(np.asarray(got), _dense_jac(prob, x, (idx, y)))
    # with constant indices the pattern is exact: one column per row
    const = jo.Problem(lambda x, y: res(x, (np.asarray(idx), y)), jacobian="sparse")
    assert const.pattern(x, y).num_colours < 20


@pytest.mark.parametrize("jacobian", ["sparse", "auto"])
def test_index_arrays_inside_a_nested_jit_are_part_of_the_cached_pattern(jacobian):
    """Patterns are cached by the analysed program; an index array closed over by a
    jitted helper is a constant of the nested program, which the cache key ignored: the
    second residual (other indices, same program text) got the first one's pattern and
    least_squares returned x = 0 with cost 24 and status CONVERGED."""
    n, m = 96, 48  # "auto" colours 48 blocks of one residual over 96 unknowns

    def residual_picking(idx):
        pick = jax.jit(lambda x: x[idx][:, None])

        def res(x, target):
            return pick(x) - target

        return res

    target = jnp.ones((m, 1))
    for idx in (np.arange(m), np.arange(m, n)):
        sol = jo.least_squares(residual_picking(idx), jnp.zeros(n), target, jacobian=jacobian)
        assert int(sol.status) == 0
        np.testing.assert_allclose(sol.params[idx], 1.0, rtol=1e-12)
        assert float(sol.cost) < 1e-20


def test_greedy_colouring_is_valid_on_random_patterns():
    rng = np.random.default_rng(9)
    for density in (0.02, 0.1, 0.5):
        p = sp.random(50, 40, density=density, random_state=rng, format="csr") != 0
        colour = greedy_colouring(p)
        for r in range(p.shape[0]):
            cols = p.indices[p.indptr[r]:p.indptr[r + 1]]
            assert len(set(colour[cols])) == cols.size


def test_weights_kernel_and_triggs_whiten_the_compressed_jacobian_exactly():
    x, a = _poses(6, 10), _poses(6, 11)
    w = jnp.asarray(np.random.default_rng(12).normal(size=(6, 6, 6)))
    w = jnp.einsum("bij,bkj->bik", w, w) + jnp.eye(6)
    kw = {"weights": w, "kernel": jo.Huber(0.3), "corrector": jo.Triggs()}
    dense = jo.Problem(invnet, jacobian="fwd", **kw).linearize(x, a)
    sparse = jo.Problem(invnet, jacobian="sparse", **kw).linearize(x, a)
    np.testing.assert_allclose(np.asarray(sparse.jac), np.asarray(dense.jac), rtol=0,
                               atol=1e-13)
    np.testing.assert_array_equal(np.asarray(sparse.res), np.asarray(dense.res))


def test_block_hessian_matches_dense_normal_matrix():
    x, a = _poses(4, 13), _poses(4, 14)
    _, lin = _coloured(invnet, x, a)
    h = lin.jac.normal()
    assert isinstance(h, BlockHessian)
    jd = np.asarray(lin.jac.dense())
    np.testing.assert_allclose(np.asarray(h.dense()), jd.T @ jd, rtol=1e-13, atol=1e-13)
    v = jnp.asarray(np.random.default_rng(15).normal(size=24))
    np.testing.assert_allclose(np.asarray(h @ v), jd.T @ jd @ np.asarray(v), atol=1e-12)
    np.testing.assert_allclose(np.asarray(lin.jac.rmatvec(lin.res)), jd.T @ np.asarray(lin.res),
                               atol=1e-12)


# ----------------------------------------------------------------------------------
# solves
# ----------------------------------------------------------------------------------
def test_auto_colours_invnet_and_keeps_small_problems_dense():
    x, a = _poses(10, 16), _poses(10, 17)
    mode, pat = jo.Problem(invnet).jacobian_mode(x, a)
    assert mode == "sparse" and pat.num_colours == 6
    assert jo.Problem(invnet).jacobian_mode(_poses(2, 1), _poses(2, 2))[0] == "fwd"


@pytest.mark.parametrize("linear_solver", [
    jo.Cholesky(), jo.SVD(), jo.CG(),
    # LU shares the batched block solve with Cholesky; QR densifies the blocks
    pytest.param(jo.LU(), marks=pytest.mark.slow), pytest.param(jo.QR(), marks=pytest.mark.slow),
], ids=lambda s: type(s).__name__)
def test_invnet_solution_equals_dense_path(linear_solver):
    x0, a = _poses(12, 18), _poses(12, 19)
    solver = jo.LM(linear_solver=linear_solver)
    sols = [jo.least_squares(invnet, x0, a, solver, jacobian=m) for m in ("sparse", "fwd")]
    assert int(sols[0].num_steps) == int(sols[1].num_steps)
    np.testing.assert_allclose(sols[0].params.data, sols[1].params.data, atol=1e-10)
    # the exact answer: X = input⁻¹
    np.testing.assert_allclose(np.asarray((sols[0].params @ a).log().data), 0.0, atol=1e-9)


@pytest.mark.parametrize("solver", [jo.GN(), jo.LM(strategy=jo.Dogleg())])
def test_banded_solution_equals_dense_path(solver):
    x0 = jnp.zeros(30)
    c = jnp.asarray(0.3)
    sols = [jo.least_squares(banded, x0, c, solver, jacobian=m) for m in ("sparse", "fwd")]
    np.testing.assert_allclose(sols[0].params, sols[1].params, atol=1e-10)
    assert float(sols[0].cost) < 1e-20


def blocks(x: jax.Array, a: jax.Array) -> jax.Array:
    """Four residuals per row of x (n, 3): 4×3 blocks, nonzero residual at the optimum."""
    return jnp.stack([x[:, 0] + 0.3 * jnp.sin(x[:, 1]) - a[:, 0],
                      x[:, 1] + 0.2 * x[:, 2] ** 2 - a[:, 1],
                      x[:, 2] + 0.1 * x[:, 0] ** 3 - a[:, 2],
                      0.5 * (x[:, 0] - x[:, 2]) - a[:, 1]], -1)


def _check_vmap_jit_and_grad(residual, x0, a, a2, sq):
    """grad through the coloured solve (jit) equals the dense path's; a vmapped coloured
    solve equals the dense solve per item."""
    def final(a_data, mode):
        return jnp.sum(sq(jo.least_squares(residual, x0, a_data, jacobian=mode).params))

    g_sparse = jax.jit(jax.grad(lambda d: final(d, "sparse")))(a)
    g_dense = jax.grad(lambda d: final(d, "fwd"))(a)
    np.testing.assert_allclose(jax.tree.leaves(g_sparse), jax.tree.leaves(g_dense), atol=1e-8)

    batch = jax.tree.map(lambda u, v: jnp.stack([u, v]), a, a2)
    solve = jax.vmap(lambda d: jo.least_squares(residual, x0, d, jacobian="sparse").params)
    out = jax.jit(solve)(batch)
    # one compilation of the dense reference solve, called per item
    dense = jax.jit(lambda d: jo.least_squares(residual, x0, d, jacobian="fwd").params)
    for k in range(2):
        item = jax.tree.map(lambda u, k=k: u[k], batch)
        np.testing.assert_allclose(jax.tree.leaves(jax.tree.map(lambda u, k=k: u[k], out)),
                                   jax.tree.leaves(dense(item)), atol=1e-10)


def test_vmap_jit_and_grad_through_the_coloured_solve():
    rng = np.random.default_rng(20)
    a, a2 = (jnp.asarray(rng.normal(size=(8, 3))) for _ in range(2))
    _check_vmap_jit_and_grad(blocks, jnp.zeros((8, 3)), a, a2, jnp.square)


@pytest.mark.slow  # SE3 solves: ~35 s of compilation
def test_vmap_jit_and_grad_through_the_coloured_se3_solve():
    _check_vmap_jit_and_grad(invnet, _poses(8, 21), _poses(8, 20), _poses(8, 22),
                             lambda p: p.data[:, :3] ** 2)


def test_unknown_jacobian_mode_names_sparse():
    with pytest.raises(ValueError, match="'sparse'"):
        jo.Problem(invnet, jacobian="colour")


def test_sparse_jacobian_is_a_pytree_of_values_only():
    _, lin = _coloured(invnet, _poses(3, 23), _poses(3, 24))
    assert isinstance(lin.jac, SparseJacobian)
    assert [leaf.shape for leaf in jax.tree.leaves(lin.jac)] == [(18, 6)]
    flat0, _ = ravel_pytree(manifold.zero_tangent(_poses(3, 23)))
    assert lin.jac.shape == (18, flat0.size)


@pytest.mark.slow  # two Hessians through SE3 solves compile for ~40 s
def test_second_derivative_through_the_coloured_exact_hessian_equals_dense():
    """The implicit rule builds the exact Hessian from one HVP per colour of H's columns
    (a BlockHessian here); its second derivatives equal those of the dense jax.hessian
    path (robust kernel: nonzero curvature terms)."""
    a = SE3.random(jax.random.PRNGKey(4), (5,), sigma=1.0)
    x0 = SE3.random(jax.random.PRNGKey(5), (5,), sigma=1.0)
    w = jax.random.normal(jax.random.PRNGKey(6), (5, 7))

    def f(d6, mode):
        inp = a.retract(jnp.broadcast_to(d6, (5, 6)))
        sol = jo.least_squares(invnet, x0, inp, jacobian=mode, kernel=jo.Cauchy(1.0))
        return jnp.sum(w * sol.params.data) + sol.cost

    hess = jax.jit(jax.hessian(f), static_argnums=1)
    np.testing.assert_allclose(hess(jnp.zeros(6), "sparse"), hess(jnp.zeros(6), "fwd"),
                               atol=1e-10)


def test_implicit_gradient_on_the_coloured_path_with_a_dense_normal_matrix():
    """Between AUTO_MIN_TANGENT (48) and SPARSE_MIN_SIZE (128) unknowns, ``jacobian="auto"``
    colours a banded Jacobian but keeps JᵀJ dense (the pattern has neither blocks nor
    CSR); the default implicit gradient crashed there (``'NoneType' object has no
    attribute 'indices'``). A smoothing chain p = argmin |p − z|² + Σ|p_i − p_i+1|²:
    (I + L) p = z with L 1 = 0, so d(Σp)/dz = (I + L)⁻¹ 1 = 1."""
    n = 64

    def res(p, z):
        return {"node": p - z[:, None], "edge": p[:-1] - p[1:]}

    def total(z):
        sol = jo.least_squares(res, jnp.zeros((n, 1)), z)
        return sol.params.sum()

    z = jnp.asarray(np.random.default_rng(0).normal(size=n))
    mode, pattern = jo.Problem(res).jacobian_mode(jnp.zeros((n, 1)), z)
    assert mode == "sparse" and pattern.groups is None and pattern.csr is None
    np.testing.assert_allclose(jax.jit(jax.grad(total))(z), np.ones(n), rtol=1e-10)


def test_a_solve_analyses_the_sparsity_pattern_once(monkeypatch):
    """``least_squares`` resolves the Jacobian mode once (``Problem.resolve``): its
    linearisations (initial, in the loop) reuse it instead of re-tracing the residual."""
    import jaxpose.optim._problem as problem_module

    calls = []

    def counting(f, x):
        calls.append(1)
        return jacobian_pattern(f, x)

    monkeypatch.setattr(problem_module, "jacobian_pattern", counting)
    x0, a = _poses(10, 0), _poses(10, 1)  # 60 tangent coordinates: the coloured path
    prob = jo.Problem(invnet)
    assert prob.jacobian_mode(x0, a)[0] == "sparse" and len(calls) == 1
    resolved = prob._resolve(x0, a)
    assert resolved.jacobian_mode(x0, a)[0] == "sparse" and len(calls) == 2
    calls.clear()
    sol = jo.least_squares(lambda x, a: invnet(x, a), x0, a)
    assert len(calls) == 1
    np.testing.assert_allclose(sol.cost, 0.0, atol=1e-12)
