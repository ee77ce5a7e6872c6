"""Synthetic pose graphs and BAL problems (jaxpose.datasets)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from io_refs import bal_project, log_matrix, pose_matrix, relative_matrix

from jaxpose.datasets import synthetic_bal, synthetic_pose_graph
from jaxpose.io import connected_components

CASES = [("SE3", "sphere"), ("SE3", "grid"), ("SE3", "circle"), ("SE2", "grid"), ("SE2", "circle")]


@pytest.mark.parametrize("kind,shape", CASES)
def test_noise_free_graph_is_consistent(kind, shape):
    g, gt = synthetic_pose_graph(kind, n_poses=150, noise=(0.0, 0.0), shape=shape, seed=1)
    d, t = (7, 6) if kind == "SE3" else (4, 3)
    assert gt.shape == (150, d) and g.poses.shape == (150, d) and g.kind == kind
    # ground truth satisfies every measurement (independent matrix arithmetic)
    rel = relative_matrix(kind, gt, g.edges)
    np.testing.assert_allclose(rel, pose_matrix(kind, g.measurements), atol=1e-12)
    # without noise, chaining odometry reproduces the ground truth; pose 0 is the identity
    np.testing.assert_allclose(g.poses, gt, atol=1e-11)
    np.testing.assert_allclose(gt[0], [0, 0, 0, 0, 0, 0, 1] if kind == "SE3" else [0, 0, 1, 0])
    np.testing.assert_array_equal(g.fixed, [0])
    np.testing.assert_array_equal(g.information, np.broadcast_to(np.eye(t), g.information.shape))
    # odometry chain plus loop closures; one connected piece; unit rotations
    ids = g.edges
    assert ((ids[:, 1] == ids[:, 0] + 1).sum() == 149) and g.n_edges > 149
    assert (np.abs(ids[:, 1] - ids[:, 0]) >= 1).all()
    assert connected_components(g).max() == 0
    rot = slice(3, 7) if kind == "SE3" else slice(2, 4)
    np.testing.assert_allclose(np.linalg.norm(gt[:, rot], axis=1), 1, atol=1e-14)
    # consecutive poses are about one unit apart
    steps = np.linalg.norm(np.diff(gt[:, : 3 if kind == "SE3" else 2], axis=0), axis=1)
    assert 0.5 < np.median(steps) < 1.5


@pytest.mark.parametrize("kind", ["SE3", "SE2"])
def test_noise_statistics_and_information(kind):
    """Residuals Log(Z⁻¹·Xi⁻¹·Xj) at the truth have covariance Σ; information = Σ⁻¹."""
    rot, trans = 0.02, 0.1
    g, gt = synthetic_pose_graph(kind, n_poses=1000, noise=(rot, trans), seed=4)
    sig = [trans] * 3 + [rot] * 3 if kind == "SE3" else [trans] * 2 + [rot]
    np.testing.assert_allclose(g.information[0], np.diag(1 / np.square(sig)))
    E = np.linalg.inv(pose_matrix(kind, g.measurements)) @ relative_matrix(kind, gt, g.edges)
    r = log_matrix(kind, E)
    np.testing.assert_allclose(r.std(0), sig, rtol=0.1)
    np.testing.assert_allclose(r.mean(0), 0, atol=0.01)
    # the initial guess (chained noisy odometry) drifts away from the truth
    assert np.abs(g.poses[-1, :2] - gt[-1, :2]).max() > 0.1


def test_residuals_agree_with_jaxpose_lie():
    """The same residuals through jaxpose.SE3 (the solver's convention), in float64."""
    jax = pytest.importorskip("jax")
    import jaxpose as jp

    g, gt = synthetic_pose_graph("SE3", n_poses=100, noise=(0.05, 0.1), seed=2, shape="grid")
    ref = log_matrix(
        "SE3",
        np.linalg.inv(pose_matrix("SE3", g.measurements)) @ relative_matrix("SE3", gt, g.edges),
    )

    def residual(x, z, e):
        X, Z = jp.SE3(x), jp.SE3(z)
        return (Z.inv() @ X[e[:, 0]].inv() @ X[e[:, 1]]).log().data

    with jax.enable_x64(True):
        r = np.asarray(jax.jit(residual)(gt, g.measurements, g.edges))
    assert r.dtype == np.float64
    np.testing.assert_allclose(r, ref, atol=1e-12)


def test_options_and_determinism():
    a, ta = synthetic_pose_graph("SE2", n_poses=100, loop_closures=7, seed=5)
    b, tb = synthetic_pose_graph("SE2", n_poses=100, loop_closures=7, seed=5)
    c, _ = synthetic_pose_graph("SE2", n_poses=100, loop_closures=7, seed=6)
    assert a.n_edges == 99 + 7
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.edges, b.edges)
    assert not np.array_equal(a.measurements, c.measurements)
    later = np.maximum(a.edges[:, 0], a.edges[:, 1])
    assert (np.diff(later) >= 0).all()  # edges ordered by their later vertex
    g, _ = synthetic_pose_graph("SE3", n_poses=64, noise=(0.01, 0.0), shape="grid")
    np.testing.assert_allclose(np.diag(g.information[0]), [1, 1, 1, 1e4, 1e4, 1e4])
    for kwargs, msg in [
        ({"kind": "SE2", "shape": "sphere"}, "needs kind='SE3'"),
        ({"shape": "torus"}, "shape must be"),
        ({"kind": "Sim3"}, "kind must be"),
        ({"n_poses": 1}, "at least 2"),
        ({"noise": (-1, 0)}, ">= 0"),
        ({"n_poses": 20, "loop_closures": 1000}, "candidate pairs"),
    ]:
        with pytest.raises(ValueError, match=msg):
            synthetic_pose_graph(**kwargs)


def test_synthetic_bal_noise_free_projections():
    problem, truth = synthetic_bal(n_cameras=12, n_points=300, obs_per_point=4, pixel_noise=0)
    px, P = bal_project(truth.cameras, truth.points, truth.camera_index, truth.point_index)
    np.testing.assert_allclose(truth.observations, px, rtol=1e-12, atol=1e-9)
    assert (P[:, 2] < -2.5).all()  # in front of every camera that sees it (BAL: P_z < 0)
    assert np.abs(truth.observations).max() < 0.5 * 900  # inside a plausible image
    assert truth.n_observations == 1200 and problem.n_observations == 1200
    # each point is seen by 4 distinct cameras; observations sorted by point then camera
    np.testing.assert_array_equal(truth.point_index, np.repeat(np.arange(300), 4))
    per_point = truth.camera_index.reshape(300, 4)
    assert (np.diff(per_point, axis=1) > 0).all()
    assert set(truth.camera_index.tolist()) == set(range(12))
    # the initial guess differs from the truth except in the intrinsics
    np.testing.assert_array_equal(problem.observations, truth.observations)
    np.testing.assert_array_equal(problem.cameras[:, 6:], truth.cameras[:, 6:])
    assert np.abs(problem.cameras[:, :6] - truth.cameras[:, :6]).max() > 1e-3
    assert 0.01 < np.abs(problem.points - truth.points).mean() < 0.1
    for kwargs, msg in [({"obs_per_point": 13}, "obs_per_point"), ({"n_points": 0}, ">= 1")]:
        with pytest.raises(ValueError, match=msg):
            synthetic_bal(n_cameras=12, **kwargs)


def test_synthetic_bal_default_size_and_noise_level():
    t = time.perf_counter()
    problem, truth = synthetic_bal(seed=1)
    elapsed = time.perf_counter() - t
    assert (truth.n_cameras, truth.n_points, truth.n_observations) == (50, 10000, 50000)
    px, _ = bal_project(truth.cameras, truth.points, truth.camera_index, truth.point_index)
    rmse = np.sqrt(np.mean((px - truth.observations) ** 2))
    assert 0.98 < rmse < 1.02  # pixel_noise = 1.0 per coordinate
    init, _ = bal_project(
        problem.cameras, problem.points, problem.camera_index, problem.point_index
    )
    assert np.sqrt(np.mean((init - truth.observations) ** 2)) > 5  # a real problem to solve
    assert elapsed < 10
