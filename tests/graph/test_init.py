"""Chordal initialisation (jaxpose.graph.chordal_initialization) against independent checks, the
information-matrix policies of the reader / API, and the `jaxpose pgo` options."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from jaxpose import read_g2o, write_g2o
from jaxpose.cli import main
from jaxpose.datasets import synthetic_pose_graph
from jaxpose.graph import chordal_initialization, initial_poses, pose_graph_cost, pose_graph_problem
from jaxpose.io import FormatError, PoseGraph, apply_information_policy

from .conftest import _pose_matrix, numpy_pose_graph_cost, random_spd


def _random_information(rng: np.random.Generator, m: int, t: int) -> np.ndarray:
    """Full (non-diagonal) SPD matrices with widely spread eigenvalues."""
    a = rng.normal(size=(m, t, t))
    return a @ np.swapaxes(a, 1, 2) + 0.05 * np.eye(t)


def _noise_free(kind: str, seed: int = 0) -> tuple[PoseGraph, np.ndarray]:
    graph, truth = synthetic_pose_graph(kind, n_poses=60, noise=(0.0, 0.0), seed=seed, shape="grid")
    rng = np.random.default_rng(seed)
    start = truth.copy()
    start[1:] = synthetic_pose_graph(kind, n_poses=60, seed=seed + 1, shape="grid")[1][1:]
    graph = dataclasses.replace(
        graph,
        poses=start,
        information=_random_information(rng, graph.n_edges, graph.information.shape[1]),
    )
    return graph, truth


def _same_pose(kind: str, a: np.ndarray, b: np.ndarray) -> float:
    """Largest entry of |A⁻¹·B − I| over the poses (independent of the storage sign)."""
    return max(
        np.abs(
            np.linalg.inv(_pose_matrix(kind, p)) @ _pose_matrix(kind, q)
            - np.eye(3 if kind == "SE2" else 4)
        ).max()
        for p, q in zip(a, b)
    )


@pytest.mark.parametrize("kind", ["SE3", "SE2"])
def test_noise_free_graph_recovered_exactly(kind):
    """Noise-free measurements, full information, far-off starting poses: the relaxation is
    tight, so the chordal poses are the true ones (the gauge: pose 0 is the true pose)."""
    graph, truth = _noise_free(kind)
    assert _same_pose(kind, graph.poses, truth) > 0.1  # the start is far off
    poses = chordal_initialization(graph)
    assert poses.shape == truth.shape
    assert _same_pose(kind, poses, truth) < 1e-10
    np.testing.assert_array_equal(poses[0], graph.poses[0])  # the anchor is untouched
    assert pose_graph_cost(graph, poses) < 1e-18


@pytest.mark.parametrize("kind", ["SE3", "SE2"])
def test_edge_only_file_recovered_up_to_the_gauge(tmp_path, kind):
    """An edge-only file (no VERTEX lines): the result equals the truth up to one rigid
    motion (the reader starts the smallest id at the identity)."""
    graph, truth = _noise_free(kind, seed=3)
    path = tmp_path / "edges.g2o"
    write_g2o(path, graph)
    text = path.read_text().splitlines()
    path.write_text("\n".join(line for line in text if not line.startswith("VERTEX")) + "\n")
    edge_only = read_g2o(path)
    poses = chordal_initialization(edge_only)
    np.testing.assert_allclose(poses[0], edge_only.poses[0])
    g = _pose_matrix(kind, truth[0]) @ np.linalg.inv(_pose_matrix(kind, poses[0]))
    moved = [g @ _pose_matrix(kind, p) for p in poses]
    err = max(np.abs(m - _pose_matrix(kind, t)).max() for m, t in zip(moved, truth))
    assert err < 1e-9


@pytest.mark.parametrize("kind", ["SE3", "SE2"])
def test_translations_minimise_the_cost_for_the_chordal_rotations(kind):
    """With the rotations fixed the translation step is the exact minimiser of 0.5·Σ rᵀΩr
    (cross blocks Ω_tR included): the gradient of the numpy reference cost with respect to
    the free translations vanishes (central differences)."""
    graph, _ = synthetic_pose_graph(kind, n_poses=12, noise=(0.05, 0.1), seed=5)
    rng = np.random.default_rng(5)
    graph = dataclasses.replace(
        graph, information=random_spd(rng, graph.n_edges, graph.information.shape[1])
    )
    poses = chordal_initialization(graph)
    dt = 3 if kind == "SE3" else 2
    h = 1e-6
    grad = []
    for v in range(1, graph.n_poses):
        for k in range(dt):
            up, down = poses.copy(), poses.copy()
            up[v, k] += h
            down[v, k] -= h
            grad.append(
                (numpy_pose_graph_cost(graph, up) - numpy_pose_graph_cost(graph, down)) / (2 * h)
            )
    scale = numpy_pose_graph_cost(graph, poses)
    assert np.max(np.abs(grad)) < 1e-6 * max(scale, 1.0)


@pytest.mark.parametrize("kind", ["SE3", "SE2"])
def test_pose_graph_cost_matches_the_reference(kind):
    graph, _ = synthetic_pose_graph(kind, n_poses=15, noise=(0.3, 0.3), seed=2)
    rng = np.random.default_rng(2)
    graph = dataclasses.replace(
        graph, information=random_spd(rng, graph.n_edges, graph.information.shape[1])
    )
    np.testing.assert_allclose(pose_graph_cost(graph), numpy_pose_graph_cost(graph), rtol=1e-12)


def test_auto_keeps_file_poses_that_cost_less():
    """Two SE2 poses joined by two inconsistent edges: the file holds the true optimum
    (scipy), which the relaxation misses, so 'auto' keeps it; 'chordal' does not."""
    z = np.array([[1.0, 0.0, 1.0, 0.0], [1.2, 0.3, np.cos(0.4), np.sin(0.4)]])
    info = np.stack([np.diag([1.0, 4.0, 9.0]), np.array([[5, 1, 2], [1, 3, 0.5], [2, 0.5, 2.0]])])
    graph = PoseGraph(
        "SE2",
        np.arange(2),
        np.array([[0, 0, 1, 0], [0, 0, 1, 0.0]]),
        np.array([[0, 1], [0, 1]]),
        z,
        info,
    )

    def f(x):
        p = np.array([[0, 0, 1, 0.0], [x[0], x[1], np.cos(x[2]), np.sin(x[2])]])
        return numpy_pose_graph_cost(graph, p)

    x = minimize(f, np.zeros(3), method="BFGS", options={"gtol": 1e-12}).x
    best = dataclasses.replace(
        graph, poses=np.array([[0, 0, 1, 0.0], [x[0], x[1], np.cos(x[2]), np.sin(x[2])]])
    )
    chordal = chordal_initialization(best)
    assert pose_graph_cost(best, chordal) > pose_graph_cost(best) + 1e-9
    poses, method = initial_poses(best, "auto")
    assert method == "odometry"
    np.testing.assert_array_equal(poses, best.poses)
    assert initial_poses(best, "chordal")[1] == "chordal"
    assert initial_poses(best, "odometry")[1] == "odometry"
    with pytest.raises(ValueError, match="init='lago'.*auto"):
        initial_poses(best, "lago")


@pytest.mark.peer
def test_rotations_match_gtsam_initialize_pose3():
    """GTSAM's InitializePose3.initializeOrientations: unweighted chordal relaxation, the
    prior on pose 0 turned into a unit-weight edge from a hard anchor at the identity.
    The same problem for jaxpose: an extra anchor vertex, an identity edge to pose 0 and
    equal isotropic information everywhere (then Ω_R weights every edge alike)."""
    gtsam = pytest.importorskip("gtsam")
    graph, _ = synthetic_pose_graph("SE3", n_poses=40, noise=(0.1, 0.1), seed=7)
    factors = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 1.0)
    for (i, j), z in zip(graph.edges.tolist(), graph.measurements):
        pose = gtsam.Pose3(gtsam.Rot3.Quaternion(z[6], z[3], z[4], z[5]), z[:3])
        factors.add(gtsam.BetweenFactorPose3(i, j, pose, noise))
    factors.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    rots = gtsam.InitializePose3.initializeOrientations(factors)
    n, m = graph.n_poses, graph.n_edges
    identity = np.array([0, 0, 0, 0, 0, 0, 1.0])
    anchored = PoseGraph(
        "SE3",
        np.arange(n + 1),
        np.tile(identity, (n + 1, 1)),
        np.concatenate([[[0, 1]], graph.edges + 1]),
        np.concatenate([identity[None], graph.measurements]),
        np.broadcast_to(np.eye(6), (m + 1, 6, 6)),
    )
    ours = chordal_initialization(anchored)
    for v in range(n):
        ref = rots.atRot3(v).matrix()
        mine = Rotation.from_quat(ours[v + 1, 3:]).as_matrix()
        np.testing.assert_allclose(mine, ref, atol=1e-9)


# ---------------------------------------------------------------------- information policies
_EDGE_TAIL = {
    "pd": "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 4 0 0 4 0 4",
    "indefinite": "1 0 0 0 0 0 1 0 0 0 0 -2 0 0 0 4 0 0 4 0 4",
    "cross": "1 0 0 3 0 0 1 0 0 0 0 1 0 0 0 4 0 0 4 0 4",  # PD blocks, indefinite overall
    "negative": "-1 0 0 0 0 0 -1 0 0 0 0 -1 0 0 0 4 0 0 4 0 4",  # τ = 3/tr(Ω_tt⁻¹) < 0
}


def _file(tmp_path, kinds):
    lines = [f"VERTEX_SE3:QUAT {v} {v} 0 0 0 0 0 1" for v in range(len(kinds) + 1)]
    lines += [
        f"EDGE_SE3:QUAT {e} {e + 1} 1 0 0 0 0 0 1 {_EDGE_TAIL[k]}" for e, k in enumerate(kinds)
    ]
    path = tmp_path / "nonpd.g2o"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_strict_error_names_the_alternatives(tmp_path):
    path = _file(tmp_path, ["pd", "indefinite", "pd", "cross"])
    with pytest.raises(FormatError, match=r"nonpd.g2o:\d+:.*2 of 4 edges.*repair.*isotropic"):
        read_g2o(path)
    with pytest.raises(ValueError, match="2 of 4 information.*'repair'.*'isotropic'"):
        apply_information_policy(_raw_information(path))


def test_repair_clips_eigenvalues_and_warns(tmp_path):
    path = _file(tmp_path, ["pd", "indefinite", "pd", "cross"])
    with pytest.warns(UserWarning, match=r"2 of 4 information matrices.*lines 7, 9\)"):
        graph = read_g2o(path, information="repair")
    raw = _raw_information(path)
    np.testing.assert_array_equal(graph.information[[0, 2]], raw[[0, 2]])  # PD: unchanged
    for e in (1, 3):
        w = np.linalg.eigvalsh(raw[e])
        fixed = graph.information[e]
        np.testing.assert_allclose(fixed, fixed.T, atol=0)
        np.linalg.cholesky(fixed)
        floor = 1e-6 * np.abs(w).max()
        assert np.linalg.eigvalsh(fixed).min() >= floor * (1 - 1e-9)
        # the Frobenius distance of the eigenvalue-clipped (nearest) matrix
        np.testing.assert_allclose(
            np.linalg.norm(fixed - raw[e]), np.linalg.norm(np.maximum(w, floor) - w), rtol=1e-9
        )
    with pytest.warns(UserWarning, match=r"apply_information_policy: 2 of 4.*edges 1, 3\)"):
        np.testing.assert_allclose(apply_information_policy(raw, "repair"), graph.information)


def _raw_information(path):
    out = []
    for line in path.read_text().splitlines():
        if line.startswith("EDGE"):
            vals = np.array(line.split()[10:], float)
            m = np.zeros((6, 6))
            m[np.triu_indices(6)] = vals
            out.append(m + np.triu(m, 1).T)
    return np.array(out)


def test_isotropic_weights_are_se_sync_traces(tmp_path):
    info = np.zeros((2, 6, 6))
    info[0] = np.diag([1.0, 2.0, 4.0, 10.0, 20.0, 40.0])
    info[1] = random_spd(np.random.default_rng(0), 1, 6)[0]
    out = apply_information_policy(info, "isotropic")
    for e in range(2):
        tau = 3.0 / np.trace(np.linalg.inv(info[e, :3, :3]))
        kappa = 3.0 / (2.0 * np.trace(np.linalg.inv(info[e, 3:, 3:])))
        np.testing.assert_allclose(out[e], np.diag([tau] * 3 + [2 * kappa] * 3), rtol=1e-12)
    np.testing.assert_allclose(out[0, 0, 0], 3 / 1.75)
    info2 = np.array([[[2.0, 0.5, 0.1], [0.5, 1.0, 0.2], [0.1, 0.2, 7.0]]])
    out2 = apply_information_policy(info2, "isotropic")
    tau2 = 2.0 / np.trace(np.linalg.inv(info2[0, :2, :2]))
    np.testing.assert_allclose(out2[0], np.diag([tau2, tau2, 7.0]), rtol=1e-12)
    # the reader: every edge of a file with non-PD matrices gets the weights, no warning
    path = _file(tmp_path, ["pd", "cross"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        graph = read_g2o(path, information="isotropic")
    np.testing.assert_allclose(graph.information[1], np.diag([1, 1, 1, 4, 4, 4.0]))
    bad = _file(tmp_path, ["pd", "negative"])
    with pytest.raises(FormatError, match="isotropic.*use information='repair'"):
        read_g2o(bad, information="isotropic")
    with pytest.raises(ValueError, match="information='lenient'.*strict"):
        read_g2o(path, information="lenient")


def test_pose_graph_problem_applies_the_policy(tmp_path):
    graph = read_g2o(_file(tmp_path, ["pd", "cross"]), information="isotropic")
    bad = dataclasses.replace(graph, information=_raw_information(_file(tmp_path, ["pd", "cross"])))
    with pytest.raises(ValueError, match="pose_graph_problem: 1 of 2.*repair"):
        pose_graph_problem(bad, information="strict")
    problem = pose_graph_problem(bad, information="isotropic")
    s = np.asarray(problem.factors[0].sqrt_info)
    np.testing.assert_allclose(np.swapaxes(s, 1, 2) @ s, graph.information, rtol=1e-12)


# ---------------------------------------------------------------------- CLI
def test_cli_init_and_information_options(tmp_path, capsys):
    path = _file(tmp_path, ["pd", "indefinite", "cross"])
    assert main(["pgo", str(path), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "not positive definite" in err and "--information repair|isotropic" in err
    out = tmp_path / "o.g2o"
    argv = ["pgo", str(path), "--quiet", "--information", "repair", "--init", "chordal"]
    rc = main([*argv, "--out", str(out)])
    assert rc == 0
    captured = capsys.readouterr()
    assert "warning:" in captured.err and "2 of 3 information matrices" in captured.err
    text = captured.out
    assert "initialisation: chordal" in text and "status converged" in text
    # the measurements are consistent: chordal is already exact, LM keeps cost 0
    result = read_g2o(out, information="repair")
    assert numpy_pose_graph_cost(result) < 1e-12
    assert main(["pgo", str(path), "--init", "spanning"]) == 2  # argparse usage error
    assert "--init" in capsys.readouterr().err


def test_cholmod_solves_several_right_hand_sides_with_one_factorisation():
    import scipy.sparse

    from jaxpose.graph import _cholmod as cholmod

    if not cholmod.available():
        pytest.skip(f"CHOLMOD unavailable: {cholmod.unavailable_reason()}")
    rng = np.random.default_rng(0)
    a = scipy.sparse.random(40, 40, density=0.1, random_state=1) + scipy.sparse.eye(40)
    h = (a @ a.T).tocsr()
    h.sort_indices()
    b = rng.normal(size=(40, 3))
    x = cholmod.solve(h.data, h.indices, h.indptr, b)
    np.testing.assert_allclose(x, np.linalg.solve(h.toarray(), b), rtol=1e-10, atol=1e-12)
    x1 = cholmod.solve(h.data, h.indices, h.indptr, b[:, 1])
    assert x1.shape == (40,)
    np.testing.assert_allclose(x1, x[:, 1], rtol=1e-13)


def test_psd_parts_matches_the_eigendecomposition_on_every_branch():
    """Square root (RᵀR = M with negative eigenvalues clipped) and pseudo-inverse of
    diagonal, positive definite full, singular and indefinite blocks, mixed in one batch."""
    from jaxpose.graph._init import _psd_parts

    rng = np.random.default_rng(7)
    a = rng.normal(size=(12, 3, 3))
    m = a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(3)  # full, positive definite
    m[:3] = np.eye(3) * rng.uniform(0.5, 2.0, (3, 1, 3))  # diagonal
    m[3] = np.diag([1.0, 0.0, 2.0])  # diagonal, singular
    b = rng.normal(size=(3, 2))
    m[4] = b @ b.T  # full, rank 2
    m[5] = np.eye(3) - 0.9 * np.ones((3, 3))  # indefinite
    root, pinv = _psd_parts(m)
    w, v = np.linalg.eigh(m)
    clipped = (v * np.clip(w, 0.0, None)[..., None, :]) @ np.swapaxes(v, -1, -2)
    np.testing.assert_allclose(np.swapaxes(root, -1, -2) @ root, clipped, atol=1e-12)
    np.testing.assert_allclose(pinv, np.linalg.pinv(m, hermitian=True), rtol=1e-9, atol=1e-9)


def _dense_block_lstsq(n, edges, bi, bj, c, anchors, x_anchor):
    """Reference for ``_block_lstsq``: the dense design matrix and ``np.linalg.lstsq``."""
    m, k, d = bi.shape
    p = c.shape[-1]
    a = np.zeros((m * k, n * d))
    for e, (i, j) in enumerate(edges):
        a[e * k:(e + 1) * k, i * d:(i + 1) * d] += bi[e]
        a[e * k:(e + 1) * k, j * d:(j + 1) * d] += bj[e]
    rhs = c.reshape(m * k, p).copy()
    free = np.setdiff1d(np.arange(n), anchors)
    cols = lambda v: (v[:, None] * d + np.arange(d)).reshape(-1)  # noqa: E731
    rhs -= a[:, cols(anchors)] @ x_anchor.reshape(-1, p)
    x = np.zeros((n, d, p))
    x[anchors] = x_anchor
    x[free] = np.linalg.lstsq(a[:, cols(free)], rhs, rcond=None)[0].reshape(-1, d, p)
    return x


@pytest.mark.parametrize("path", ["dense", "cholmod", "scipy"])
def test_block_least_squares_matches_the_dense_solution(monkeypatch, path):
    # repeated edges, an edge in both directions, a self-loop, edges between anchors and
    # a vertex seen only by zero-weight rows (the ridge fallback): the normal equations
    # (dense for small systems, else sparse with CHOLMOD or SciPy) against the dense
    # design matrix and np.linalg.lstsq
    from jaxpose.graph import _cholmod as cholmod
    from jaxpose.graph import _init
    from jaxpose.graph._init import _block_lstsq

    if path == "cholmod" and not cholmod.available():
        pytest.skip(f"CHOLMOD unavailable: {cholmod.unavailable_reason()}")
    if path != "dense":
        monkeypatch.setattr(_init, "_DENSE_MAX", 0)
    if path == "scipy":
        monkeypatch.setattr(cholmod, "available", lambda: False)
    rng = np.random.default_rng(4)
    n, k, d, p = 7, 4, 3, 2
    edges = np.array([[0, 1], [1, 2], [1, 2], [2, 1], [3, 3], [2, 4], [4, 5], [0, 5],
                      [5, 3], [0, 6], [1, 6], [6, 0]])
    m = len(edges)
    bi, bj, c = rng.normal(size=(m, k, d)), rng.normal(size=(m, k, d)), rng.normal(size=(m, k, p))
    anchors = np.array([0, 5])
    x_anchor = rng.normal(size=(2, d, p))
    got = _block_lstsq(n, edges, bi, bj, c, anchors, x_anchor)
    want = _dense_block_lstsq(n, edges, bi, bj, c, anchors, x_anchor)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)
    # vertex 6 only in zero-weight rows: singular normal equations → the ridge, X₆ = 0
    zero = np.isin(np.arange(m), [9, 10, 11])
    bi[zero], bj[zero] = 0.0, 0.0
    got = _block_lstsq(n, edges, bi, bj, c, anchors, x_anchor)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got[6], 0.0, atol=1e-12)
    want = _dense_block_lstsq(n, edges[~zero], bi[~zero], bj[~zero], c[~zero], anchors, x_anchor)
    np.testing.assert_allclose(got[:6], want[:6], rtol=1e-8, atol=1e-10)


def test_host_cost_and_chordal_take_a_tiny_scaled_quaternion():
    """A measurement quaternion scaled by 1e-200 (read_g2o normalises such; an in-memory
    PoseGraph may hold one): the host NumPy rotation matrix divided by a norm that
    underflowed to 0, so pose_graph_cost was NaN and chordal_initialization raised "SVD did
    not converge" while the JAX cost was right."""
    from jaxpose.io import PoseGraph

    q = np.array([0.0, 0.0, np.sin(0.3), np.cos(0.3)])
    poses = np.array([[0, 0, 0, 0, 0, 0, 1.0], [1, 0, 0, *q], [2, 1, 0, 0, 0, 0, 1.0]])

    def graph(scale):
        meas = np.array([[1, 0, 0, *(q * scale)], [1, 0.5, 0, 0, 0, 0, 1.0]])
        return PoseGraph("SE3", np.arange(3), poses, np.array([[0, 1], [1, 2]]), meas,
                         np.stack([np.eye(6)] * 2))

    unit, tiny = graph(1.0), graph(1e-200)
    want = pose_graph_cost(unit)
    assert np.isfinite(want) and want > 0.1
    assert pose_graph_cost(tiny) == pytest.approx(want, rel=1e-14)
    np.testing.assert_allclose(chordal_initialization(tiny), chordal_initialization(unit),
                               rtol=0, atol=1e-14)
