"""Linearisation and block-sparse algebra of factor graphs vs dense autodiff references.

One jitted function per graph evaluates everything the LM step needs (residuals,
Jacobian blocks, CSR values of H, gradient, H·v, diagonal blocks, the three linear solvers)
next to a dense reference: ``jax.jacfwd`` of the whole graph's whitened residual as a
function of the full tangent vector (built in ``conftest.py`` without the code under test).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.graph import FactorGraph, linearize
from jaxpose.graph import _linear as linear
from jaxpose.graph._problem import block_diagonal, csr_values, gradient, hessian_vector
from jaxpose.optim import Huber

from .conftest import (
    FAST_COMPILE,
    assemble_jacobian,
    csr_to_dense,
    dense_residual_fn,
    layout,
    mixed_problem,
)

LAMBDA = 1e-2  # damping of the linear-solver checks (the graphs have gauge freedom)


def _evaluate(info):
    """A jitted graph → (everything the LM step uses, dense references)."""

    def run(graph, v):
        st = graph.structure
        lin = linearize(graph, graph.variables)
        ref = dense_residual_fn(graph, graph.variables, info)
        zero = jnp.zeros(graph.size, lin.cost.dtype)
        data = csr_values(graph, lin)
        blocks = block_diagonal(graph, lin)
        g = gradient(graph, lin)
        # damped system (H + λ·diag(H) + I) x = −g through each linear solver
        damped = data.at[st.diag_pos].add(LAMBDA * data[st.diag_pos] + 1.0)
        dvec = jnp.concatenate([jax.vmap(jnp.diag)(b).reshape(-1) for b in blocks])
        pre = tuple(b + jax.vmap(jnp.diag)(LAMBDA * jax.vmap(jnp.diag)(b) + 1.0) for b in blocks)
        x_pcg, its = linear.solve_pcg(
            lambda u: hessian_vector(graph, lin, u) + (LAMBDA * dvec + 1.0) * u,
            -g, linear.block_jacobi(pre), rtol=1e-12, max_iters=500,
        )
        return dict(
            lin=lin,
            csr=data,
            grad=g,
            hv=hessian_vector(graph, lin, v),
            blocks=blocks,
            J_ref=jax.jacfwd(ref)(zero),
            r_ref=ref(zero),
            x_pcg=x_pcg,
            pcg_its=its,
            x_sparse=linear.solve_sparse_direct(damped, st.csr_indices, st.csr_indptr, -g),
            x_dense=linear.solve_dense(damped, st.csr_indices, st.csr_indptr, -g),
        )

    return jax.jit(run, compiler_options=FAST_COMPILE)


def _check_algebra(graph: FactorGraph, out: dict, v: np.ndarray, free_cols: np.ndarray,
                   weights: np.ndarray | None = None, rtol: float = 1e-10) -> np.ndarray:
    """Assert every block-sparse quantity equals its dense counterpart; returns J̃."""
    J_ref = np.asarray(out["J_ref"]) * free_cols[None, :]  # fixed variables: zero columns
    r_ref = np.asarray(out["r_ref"])
    if weights is not None:  # IRLS: rows scaled by sqrt(ρ'(s)) of their factor
        J_ref, r_ref = J_ref * weights[:, None], r_ref * weights
    scale = np.abs(J_ref).max()
    J = assemble_jacobian(graph, out["lin"].jacobians)
    np.testing.assert_allclose(J, J_ref, rtol=0, atol=rtol * scale)
    r = np.concatenate([np.asarray(x).reshape(-1) for x in out["lin"].residuals])
    np.testing.assert_allclose(r, r_ref, rtol=0, atol=rtol * np.abs(r_ref).max())

    H = J_ref.T @ J_ref
    st = graph.structure
    H_csr = csr_to_dense(out["csr"], st.csr_indices, st.csr_indptr, graph.size)
    np.testing.assert_allclose(H_csr, H, rtol=0, atol=rtol * np.abs(H).max())
    np.testing.assert_allclose(out["grad"], J_ref.T @ r_ref, rtol=0,
                               atol=rtol * np.abs(J_ref.T @ r_ref).max())
    np.testing.assert_allclose(out["hv"], H @ v, rtol=0, atol=rtol * np.abs(H @ v).max())
    # diagonal blocks, per type in sorted-name order
    for (name, (off, n, d)), blk in zip(layout(graph.variables).items(), out["blocks"],
                                        strict=True):
        want = np.stack([H[off + i * d : off + (i + 1) * d, off + i * d : off + (i + 1) * d]
                         for i in range(n)])
        np.testing.assert_allclose(blk, want, rtol=0, atol=rtol * np.abs(H).max(), err_msg=name)

    # linear solvers vs numpy on the damped system
    A = H + np.diag(LAMBDA * np.diag(H) + 1.0)
    x = np.linalg.solve(A, -(J_ref.T @ r_ref))
    xs = np.abs(x).max()
    np.testing.assert_allclose(out["x_dense"], x, rtol=0, atol=1e-9 * xs)
    np.testing.assert_allclose(out["x_sparse"], x, rtol=0, atol=1e-9 * xs)
    np.testing.assert_allclose(out["x_pcg"], x, rtol=0, atol=1e-8 * xs)
    assert 0 < int(out["pcg_its"]) < 500
    return J


def _free_cols(graph: FactorGraph) -> np.ndarray:
    return np.concatenate([np.repeat(np.asarray(f), d)
                           for f, d in zip(graph.structure.free, graph.structure.dims,
                                           strict=True)])


def _huber_weights(graph: FactorGraph, r_ref: np.ndarray) -> tuple[np.ndarray, list]:
    """Per residual row sqrt(ρ'(s)) (Huber: 1 for s ≤ δ², (δ/√s)^½ beyond; 1 without a
    kernel), s = |r̃|² of the row's factor; and s per factor group."""
    w, s_all, row = [], [], 0
    for f in graph.factors:
        r = f.sqrt_info.shape[-1] if f.sqrt_info is not None else 7  # (Sim3 has no Ω)
        s = (r_ref[row : row + f.count * r].reshape(f.count, r) ** 2).sum(1)
        if f.kernel is None:
            wf = np.ones_like(s)
        else:
            d = f.kernel.delta
            wf = np.where(s <= d**2, 1.0, np.sqrt(d / np.sqrt(s)))
        w.append(np.repeat(wf, r))
        s_all.append(s)
        row += f.count * r
    return np.concatenate(w), s_all


def _huber_cost(graph: FactorGraph, s_all: list) -> float:
    total = 0.0
    for f, s in zip(graph.factors, s_all, strict=True):
        if f.kernel is None:
            total += 0.5 * s.sum()
        else:
            d = f.kernel.delta
            total += 0.5 * np.sum(np.where(s <= d**2, s, 2 * d * np.sqrt(s) - d**2))
    return total


def _subgraph(graph: FactorGraph, keep: list[int], fixed=None) -> FactorGraph:
    factors = [graph.factors[k] for k in keep]
    names = {s for f in factors for s in f.slots}
    return FactorGraph(factors, {k: v for k, v in graph.variables.items() if k in names},
                       fixed=fixed)


def test_jacobians_normal_equations_and_linear_solvers_match_dense_references():
    """SE3 and SE2 between factors (SE2 with Huber(1) and one outlier edge), a factor
    mixing SE3 with a 3-vector variable, a vector prior. Then the same graph (same
    compiled function) with fixed variables: zero Jacobian columns and zero steps."""
    full, info = mixed_problem(seed=0, se2_kernel=Huber(1.0))
    keep = [0, 1, 3, 5]  # between_se3, between_se2, landmark, prior_point
    graph = _subgraph(full, keep)
    assert graph.structure.names == ("point", "pose2", "pose3")
    assert graph.size == 4 * 3 + 4 * 3 + 5 * 6
    run = _evaluate([info[k] for k in keep])
    v = np.random.default_rng(1).normal(size=graph.size)
    out = run(graph, v)

    # robust kernel: inliers keep weight 1, the outlier edge is downweighted
    w, s = _huber_weights(graph, np.asarray(out["r_ref"]))
    s_se2 = s[1]
    assert np.all(s_se2[:-1] < 1.0) and s_se2[-1] > 10.0, s_se2
    w_se2 = w[6 * 6 : 6 * 6 + 4 * 3].reshape(4, 3)[:, 0]
    assert np.all(w_se2[:-1] == 1.0) and w_se2[-1] < 0.6
    np.testing.assert_allclose(float(out["lin"].cost), _huber_cost(graph, s), rtol=1e-12)
    assert float(out["lin"].cost) < 0.5 * sum(x.sum() for x in s)  # below the plain cost

    J = _check_algebra(graph, out, v, np.ones(graph.size), weights=w)
    assert np.all(np.abs(J).sum(0) > 0)  # every variable is observed
    # H has the block pattern of the graph: pose3 0 and 2 share no factor
    off = layout(graph.variables)["pose3"][0]
    st = graph.structure
    H = csr_to_dense(out["csr"], st.csr_indices, st.csr_indptr, graph.size)
    assert np.all(H[off : off + 6, off + 12 : off + 18] == 0)
    assert st.nnz < graph.size**2

    # fixed variables: the fixed mask is a leaf, so this reuses the compiled function
    fixed = {"pose3": [1, 4], "point": [3], "pose2": [0]}
    g2 = _subgraph(full, keep, fixed=fixed)
    out = run(g2, v)
    free = _free_cols(g2)
    assert free.sum() == g2.size - 2 * 6 - 3 - 3
    J = _check_algebra(g2, out, v, free, weights=w)
    assert np.all(J[:, free == 0] == 0)
    for key in ("x_dense", "x_sparse", "x_pcg"):  # zero steps for fixed variables
        assert np.all(np.asarray(out[key])[free == 0] == 0), key


@pytest.mark.slow
def test_all_variable_and_factor_types_with_sim3_and_priors():
    """The full mixed graph: SE3/SE2/Sim3 between factors, SE3 prior, landmark, vector prior."""
    graph, info = mixed_problem(seed=3, fixed={"sim3": [2]})
    assert graph.structure.names == ("point", "pose2", "pose3", "sim3")
    v = np.random.default_rng(3).normal(size=graph.size)
    out = _evaluate(info)(graph, v)
    _check_algebra(graph, out, v, _free_cols(graph))


@pytest.mark.slow
def test_float32_linearization():
    graph, info = mixed_problem(seed=4, dtype=jnp.float32)
    graph = _subgraph(graph, [0, 1, 3, 5])
    info = [info[k] for k in [0, 1, 3, 5]]
    v = np.random.default_rng(4).normal(size=graph.size).astype(np.float32)
    out = _evaluate(info)(graph, v)
    # H is formed in float64 (x64 is on in the tests): graph._problem.normal_dtype
    assert out["lin"].cost.dtype == jnp.float32 and out["csr"].dtype == jnp.float64
    J_ref = np.asarray(out["J_ref"], np.float64)
    J = assemble_jacobian(graph, out["lin"].jacobians)
    np.testing.assert_allclose(J, J_ref, rtol=0, atol=1e-5 * np.abs(J_ref).max())
    H = J_ref.T @ J_ref
    st = graph.structure
    H_csr = csr_to_dense(out["csr"], st.csr_indices, st.csr_indptr, graph.size)
    np.testing.assert_allclose(H_csr, H, rtol=0, atol=1e-5 * np.abs(H).max())
