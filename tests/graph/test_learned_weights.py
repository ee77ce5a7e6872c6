"""The learned-edge-weights example (notebooks/_examples/learned_weights.py): the untrained
network gives a uniform fraction of the kernel's IRLS weights (so training starts at the
kernel's solution), and the features are those documented."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxpose.datasets import synthetic_pose_graph
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
    w = np.asarray(net(jnp.asarray(feats)))  # a uniform fraction of ρ': the same minimiser
    np.testing.assert_allclose(w / feats[:, 3], 1.0 / (1.0 + np.exp(-4.0)), rtol=1e-12)
