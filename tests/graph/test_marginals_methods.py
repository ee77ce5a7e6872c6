"""``jaxpose.graph.marginals``: the Schur path (kept poses, a fixed eliminated
point) against numpy's inverse of the dense Gauss–Newton matrix, the derivative of the
methods that have one against a closed form, a clear error from the methods that have
none, and non-integer pair indices refused (they were truncated).

Reference: H = JᵀJ with J = ``jax.jacfwd`` of the whole graph's whitened residual
(``conftest.dense_residual_fn``), inverted by numpy; scaling every information matrix by
s² scales Σ by 1/s², so dΣ/ds = −2Σ and d²Σ/ds² = 6Σ at s = 1.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.graph import Factor, FactorGraph, between_residual, marginals
from jaxpose.lie import SE2

from .conftest import dense_covariance, random_poses, random_spd


def _observe(x: SE2, p: jax.Array, z: jax.Array) -> jax.Array:
    return x.inv().act(p) - z


def _graph():
    """4 SE2 poses, 5 eliminated 2-D points; pose 0 and point 2 fixed."""
    rng = np.random.default_rng(1)
    e = np.array([[0, 1], [1, 2], [2, 3]])
    obs = np.array([[0, 0], [0, 1], [1, 1], [1, 2], [2, 2], [2, 3], [3, 3], [3, 4], [0, 4],
                    [1, 0]])
    info = [random_spd(rng, len(e), 3), random_spd(rng, len(obs), 2)]
    variables = {"pose": SE2(jnp.asarray(random_poses(rng, "SE2", 4, 0.5))),
                 "point": jnp.asarray(2.0 * rng.normal(size=(5, 2)))}
    factors = [
        Factor(between_residual, [("pose", e[:, 0]), ("pose", e[:, 1])],
               data=SE2(jnp.asarray(random_poses(rng, "SE2", len(e), 0.5))),
               information=info[0]),
        Factor(_observe, [("pose", obs[:, 0]), ("point", obs[:, 1])],
               data=jnp.asarray(rng.normal(size=(len(obs), 2))), information=info[1]),
    ]
    graph = FactorGraph(factors, variables, fixed={"pose": [0], "point": [2]},
                        eliminate="point")
    return graph, info


def _reference_pose_blocks(graph, info):
    cov = dense_covariance(graph, info)
    st = graph.structure
    o = st.offsets[st.names.index("pose")]
    return cov, np.stack([cov[o + 3 * i : o + 3 * i + 3, o + 3 * i : o + 3 * i + 3]
                          for i in range(4)]), o


def _scaled(graph, s):
    factors = tuple(eqx.tree_at(lambda f: f.sqrt_info, f, f.sqrt_info * s)
                    for f in graph.factors)
    return eqx.tree_at(lambda g: g.factors, graph, factors)


def test_schur_marginals_with_fixed_point_match_numpy_inverse():
    graph, info = _graph()
    cov, ref, o = _reference_pose_blocks(graph, info)
    m = marginals(graph, None, variables="pose", pairs=np.array([[1, 3]]), method="schur")
    np.testing.assert_allclose(m.covariances["pose"], ref, rtol=1e-10, atol=1e-14)
    sl = np.r_[o + 3 : o + 6, o + 9 : o + 12]
    np.testing.assert_allclose(m.joint[0], cov[np.ix_(sl, sl)], rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("method", ["schur", "sparse"])
def test_host_methods_refuse_derivatives_clearly(method):
    """grad/jacfwd of a "schur" or "sparse" marginal raised JAX's internal "Pure callbacks
    do not support JVP"; now the error names the method and the ones that differentiate.
    A derivative that does not pass through the covariance still works."""
    graph, _ = _graph()

    def total(s):
        cov = marginals(_scaled(graph, s), None, variables="pose", method=method)
        return jnp.sum(cov.covariances["pose"][2])

    match = rf"marginals\(method='{method}'\) is not differentiable.*'dense'.*'pcg'"
    for how in (jax.grad, jax.jacfwd):
        with pytest.raises(Exception, match=match):
            how(total)(1.0)
    got = jax.grad(lambda s: s * total(1.0))(2.0)  # the covariance has no tangent
    assert float(got) == pytest.approx(float(total(1.0)), rel=1e-12)


@pytest.mark.parametrize("method", ["dense", "sparse", "pcg"])
def test_an_open_gauge_is_refused(method):
    """Between factors only and no pose fixed: H is singular. The dense path's Cholesky
    "succeeded" on rounding and returned finite covariances of 1e14 (pose2example), the
    sparse path NaN, PCG an error about CG (docs-claims audit); now one ValueError."""
    from jaxpose.graph import pose_graph_problem
    from jaxpose.io import read_g2o

    from .conftest import data_file

    graph = pose_graph_problem(read_g2o(data_file("pose2example.txt")), fix="none")
    with pytest.raises(ValueError, match=r"marginals: .*gauge freedom.*fix a pose"):
        marginals(graph, None, "pose", method=method)
    fixed = pose_graph_problem(read_g2o(data_file("pose2example.txt")))
    assert np.all(np.isfinite(marginals(fixed, None, "pose", method=method)
                              .covariances["pose"]))


def test_non_integer_pair_index_raises():
    """((type, 1.7), ...) was truncated to index 1 (a covariance of the wrong pose)."""
    graph, _ = _graph()
    with pytest.raises(ValueError, match=r"pairs\[0\].*integer"):
        marginals(graph, None, variables="pose", pairs=[(("pose", 1.7), ("pose", 3))])

