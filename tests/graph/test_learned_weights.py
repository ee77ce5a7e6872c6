"""The learned-edge-weights example (notebooks/_examples/learned_weights.py): the untrained
network gives the kernel's IRLS weights (so training starts at the kernel's solution) and
its output corrects them in log-odds, the features are those documented, and the training
target is each draw's own clean optimum."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxpose.datasets import synthetic_pose_graph
from jaxpose.io import PoseGraph
from jaxpose.optim import Cauchy
from notebooks._examples import learned_weights as lw


def test_untrained_network_returns_the_kernel_weights_and_features_are_documented():
    graph, truth = synthetic_pose_graph("SE2", n_poses=12, seed=3)
    kernel = Cauchy(2.0)
    feats = lw.edge_features(graph, truth, kernel)
    edges = np.asarray(graph.edges)
    s = lw.squared_residuals(graph, truth)
    # s = rᵀΩr by hand for one edge: Log(Z⁻¹ Xi⁻¹ Xj) in se2's [x, y, θ] layout
    i, j = edges[5]
    xi, xj, z = (np.asarray(v) for v in (truth[i], truth[j], graph.measurements[5]))
    rot = lambda c, s_: np.array([[c, -s_], [s_, c]])  # noqa: E731
    ang = lambda x: np.arctan2(x[3], x[2])  # noqa: E731
    dth = ang(xj) - ang(xi) - ang(z)
    dt = rot(*z[2:]).T @ (rot(*xi[2:]).T @ (xj[:2] - xi[:2]) - z[:2])
    th = np.arctan2(np.sin(dth), np.cos(dth))
    # se2 Log: translation part V(θ)⁻¹ dt
    a, b = (np.sin(th) / th, (1 - np.cos(th)) / th) if abs(th) > 1e-12 else (1.0, 0.0)
    v = np.array([[a, -b], [b, a]])
    r = np.concatenate([np.linalg.solve(v, dt), [th]])
    np.testing.assert_allclose(s[5], r @ np.asarray(graph.information[5]) @ r, rtol=1e-8)
    tau = lw.threshold("SE2")
    gap = np.abs(edges[:, 1] - edges[:, 0])
    np.testing.assert_allclose(feats[:, 0], np.log1p(s / tau), rtol=1e-12)
    np.testing.assert_allclose(feats[:, 2], np.log(gap) / np.log(12), rtol=1e-12)
    np.testing.assert_allclose(feats[:, 3], 1.0 / (1.0 + s / 4.0), rtol=1e-12)  # Cauchy ρ'
    net = lw.WeightNet(jax.random.PRNGKey(0))
    w = np.asarray(net(jnp.asarray(feats)))  # ρ' itself (capped below 1): the same minimiser
    np.testing.assert_allclose(w, np.minimum(feats[:, 3], lw.RHO1_CAP), rtol=1e-12)


def test_network_output_corrects_the_kernel_weight_in_log_odds():
    # a constant MLP output b moves every weight to σ(logit(ρ') + b) = ρ'/(ρ' + (1 − ρ')e⁻ᵇ),
    # so an edge the kernel down-weighted to 0.01 can rise above a kept one's weight
    rho1 = np.array([1e-200, 0.01, 0.3, 0.9, 1.0])
    feats = jnp.asarray(np.column_stack([np.zeros((5, 3)), rho1]))
    net = lw.WeightNet(jax.random.PRNGKey(1))
    for b in (-3.0, 0.0, 5.0):
        shifted = eqx.tree_at(lambda m: m.mlp.layers[-1].bias, net, jnp.asarray(b))
        cap = np.minimum(rho1, lw.RHO1_CAP)
        expect = cap / (cap + (1.0 - cap) * np.exp(-b))
        np.testing.assert_allclose(np.asarray(shifted(feats)), expect, rtol=1e-12)
    # differentiable in the network's parameters where ρ' is capped or tiny (no NaN)
    grads = eqx.filter_grad(lambda m: jnp.sum(m(feats)))(net)
    leaves = jax.tree.leaves(grads)
    assert leaves and all(np.all(np.isfinite(g)) for g in leaves)


def test_training_target_is_the_draws_graph_without_its_wrong_loop_closures():
    # the oracle weighting (1 true edge, 0 wrong loop closure) solved from a kernel's
    # solution equals LM on the draw's graph with the wrong edges deleted
    graph, _ = synthetic_pose_graph("SE2", n_poses=30, seed=1)
    start = np.asarray(graph.poses)
    (draw,) = lw.make_draws(graph, 0.3, [7], start, 100)
    keep = draw.true_edges()
    assert keep.dtype == float and set(np.unique(keep)) == {0.0, 1.0}
    np.testing.assert_array_equal(np.flatnonzero(keep == 0), draw.outliers)
    assert draw.outliers.size == round(0.3 * np.sum(np.abs(np.diff(graph.edges, axis=1)) != 1))
    kernel = Cauchy(2.0)
    base = draw.kernel_solve("cauchy", 2.0)
    target, weights = lw.learned_solver(draw, base, kernel)(keep)
    np.testing.assert_array_equal(weights, keep)
    g = draw.graph
    kept = keep.astype(bool)
    pruned = PoseGraph(kind=g.kind, vertex_ids=g.vertex_ids, poses=base, edges=g.edges[kept],
                       measurements=g.measurements[kept], information=g.information[kept])
    ref = lw.clean_optimum(pruned, base, 100)
    np.testing.assert_allclose(target, ref, atol=1e-8)
    np.testing.assert_allclose(draw.oracle_solution(base), ref, atol=1e-8)  # what trains


# ----------------------------------------------------------------------------------
# The bundle-adjustment example (notebooks/_examples/learned_ba_weights.py)
# ----------------------------------------------------------------------------------
def _ba():
    from jaxpose.datasets import synthetic_bal
    from notebooks._examples import learned_ba_weights as lb

    clean = lb.held_at_truth(*synthetic_bal(6, 40, 3, lb.PIXEL_NOISE, seed=0))
    return lb, clean


def test_ba_gauge_cameras_are_held_at_their_true_values():
    """With cameras 0 and 1 held at their true values the uncorrupted problem's optimum
    fits the 1-pixel noise (cost within the χ² spread of ½·(residuals − unknowns)); held
    at synthetic_bal's perturbed values they contradict the data (cost several times it)."""
    from jaxpose.datasets import synthetic_bal
    from jaxpose.graph import bundle_adjustment_problem, solve

    lb, clean = _ba()
    start, truth = synthetic_bal(6, 40, 3, lb.PIXEL_NOISE, seed=0)
    np.testing.assert_array_equal(clean.cameras[list(lb.FIXED)], truth.cameras[list(lb.FIXED)])
    np.testing.assert_array_equal(clean.cameras[2:], start.cameras[2:])
    dof = 2 * clean.observations.shape[0] - (9 * (6 - len(lb.FIXED)) + 3 * 40)
    costs = [float(solve(bundle_adjustment_problem(p, fixed_cameras=lb.FIXED),
                         **lb._solve_options(60)).cost) for p in (clean, start)]
    assert abs(costs[0] - 0.5 * dof) < 0.5 * 5 * np.sqrt(2 * dof), (costs, dof)
    assert costs[1] > 3 * costs[0], costs


def test_ba_outliers_and_features_are_documented():
    """Outliers: the seeded fraction of observations, each moved by at most OUTLIER_PX per
    coordinate, the others unchanged; features: log(1 + s/τ), τ/(s + τ), the error
    against the median of the point's other observations, and ρ'(s), with s the squared
    reprojection error recomputed here with NumPy's BAL camera model."""
    from jaxpose.graph import bundle_adjustment_problem
    from jaxpose.io._bal import _bal_project_numpy

    lb, clean = _ba()
    bad, out = lb.corrupt_observations(clean, 0.25, seed=3)
    again, out2 = lb.corrupt_observations(clean, 0.25, seed=3)
    np.testing.assert_array_equal(out, out2)
    np.testing.assert_array_equal(bad.observations, again.observations)
    m = clean.observations.shape[0]
    assert out.size == round(0.25 * m)
    moved = np.flatnonzero(np.any(bad.observations != clean.observations, axis=1))
    np.testing.assert_array_equal(moved, out)
    assert np.abs(bad.observations - clean.observations).max() <= lb.OUTLIER_PX
    kernel = Cauchy(3.0)
    variables = bundle_adjustment_problem(bad).variables
    feats = lb.observation_features(bad, variables, kernel)
    pred = _bal_project_numpy(bad.cameras, bad.points, bad.camera_index, bad.point_index)
    s = np.sum((pred - bad.observations) ** 2, 1)
    tau = lb.threshold()
    np.testing.assert_allclose(feats[:, 0], np.log1p(s / tau), rtol=1e-9)
    np.testing.assert_allclose(feats[:, 1], tau / (s + tau), rtol=1e-9)
    k = 7
    others = [i for i in np.flatnonzero(bad.point_index == bad.point_index[k]) if i != k]
    np.testing.assert_allclose(feats[k, 2], np.log1p(s[k] / (np.median(s[others]) + tau)),
                               rtol=1e-9)
    np.testing.assert_allclose(feats[:, 3], 1.0 / (1.0 + s / 9.0), rtol=1e-9)  # Cauchy ρ'


def test_ba_weights_train_through_the_solve_and_the_oracle_removes_the_outliers():
    """The oracle target (outliers at weight 0) is BA on the problem without them; a few
    Adam steps through the Schur-eliminated solve lower the training loss; the untrained
    network reproduces the kernel's solution."""
    from jaxpose.graph import bundle_adjustment_problem, solve
    from jaxpose.io import BALProblem

    lb, clean = _ba()
    (draw,) = lb.make_draws(clean, 0.2, [5], 60)
    base = draw.kernel_solve("huber", 2.0)
    keep = draw.true_observations().astype(bool)
    p = draw.problem
    fewer = BALProblem(p.cameras, p.points, p.camera_index[keep], p.point_index[keep],
                       p.observations[keep])
    graph = bundle_adjustment_problem(fewer, fixed_cameras=lb.FIXED)
    graph = eqx.tree_at(lambda g: g.variables, graph, dict(base))
    ref = solve(graph, **lb._solve_options(60)).variables["point"]
    np.testing.assert_allclose(draw.oracle_solution(base), ref, atol=1e-8)

    out = lb.experiment(6, 40, 3, rate=0.2, train_seeds=[5], test_seeds=[6], steps=6,
                        kernels=("huber",), scales=(0.5, 1.0))
    losses = out["fit"].losses
    assert losses[-1] < losses[0]
    np.testing.assert_allclose(out["test"]["untrained"], out["test"]["huber"], rtol=1e-3)
    assert set(out["test"]) == {"huber", "untrained", "learned", "oracle"}
