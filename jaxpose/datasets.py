"""Synthetic, seeded test problems: pose graphs and bundle-adjustment (BAL) problems.

Everything is generated with ``numpy.random.default_rng(seed)`` in float64, so the same seed
gives the same problem on every machine, independently of ``jax_enable_x64``. The results
use the same containers as the file readers (:class:`jaxpose.io.PoseGraph`,
:class:`jaxpose.io.BALProblem`), so they can be written with ``write_g2o``/``write_bal``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .io._bal import BALProblem, _bal_project_numpy
from .io._g2o import PoseGraph
from .lie._numpy import (
    compose,
    compose1,
    inverse,
    normalize,
    quat_from_matrix,
    quat_mul,
    rotvec_from_quat,
    se2_exp,
    se3_exp,
    so3_exp,
)

__all__ = ["corrupt_loop_closures", "synthetic_bal", "synthetic_pose_graph"]

# ----------------------------------------------------------------------------- numpy Lie helpers


def _random_quat(rng: np.random.Generator, n: int) -> np.ndarray:
    return normalize(rng.normal(size=(n, 4)))


def _yaw_quat(yaw: np.ndarray) -> np.ndarray:
    z = np.zeros_like(yaw)
    return np.stack([z, z, np.sin(yaw / 2), np.cos(yaw / 2)], -1)


# ----------------------------------------------------------------------------- pose graphs


def _trajectory(
    kind: str, shape: str, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Ground-truth poses (n, 7)/(n, 4) and candidate loop-closure pairs (i, j), i < j − 1."""
    if shape in ("sphere", "circle"):
        m = max(4, int(round(np.sqrt(n))))  # poses per ring / lap; step length about 1
        k = np.arange(n)
        lon = 2 * np.pi * (k % m) / m
        radius = m / (2 * np.pi)
        pairs = [(i - m, i) for i in range(m, n)]  # same longitude, previous ring / lap
        if shape == "circle":
            pos = np.stack([radius * np.cos(lon), radius * np.sin(lon), np.zeros(n)], -1)
            yaw = lon + np.pi / 2  # heading along the circle
            if kind == "SE2":
                return np.stack([pos[:, 0], pos[:, 1], np.cos(yaw), np.sin(yaw)], -1), pairs
            return np.concatenate([pos, _yaw_quat(yaw)], -1), pairs
        rings = -(-n // m)
        lat = -np.pi / 2 + np.pi * (k // m + 0.5) / rings
        out = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], -1)
        east = np.stack([-np.sin(lon), np.cos(lon), np.zeros(n)], -1)
        R = np.stack([east, np.cross(out, east), out], -1)  # columns: heading, left, outward
        return np.concatenate([radius * out, quat_from_matrix(R)], -1), pairs
    # grid: a boustrophedon walk through a cube (SE3) or square (SE2) of unit spacing
    dim = 3 if kind == "SE3" else 2
    side = int(np.ceil(n ** (1 / dim) - 1e-9))
    cells: list[tuple[int, ...]] = []
    if dim == 2:
        for y in range(side):
            xs = range(side) if y % 2 == 0 else range(side - 1, -1, -1)
            cells += [(x, y) for x in xs]
    else:
        row = 0
        for z in range(side):
            ys = range(side) if z % 2 == 0 else range(side - 1, -1, -1)
            for y in ys:
                xs = range(side) if row % 2 == 0 else range(side - 1, -1, -1)
                cells += [(x, y, z) for x in xs]
                row += 1
    cells = cells[:n]
    index = {c: i for i, c in enumerate(cells)}
    pairs = []
    for j, c in enumerate(cells):
        for axis in range(dim):
            nb = tuple(v - (a == axis) for a, v in enumerate(c))
            i = index.get(nb, -1)
            if i >= 0 and abs(i - j) > 1:
                pairs.append((min(i, j), max(i, j)))
    pairs.sort(key=lambda p: (p[1], p[0]))
    pos = np.asarray(cells, np.float64)
    if kind == "SE2":
        th = rng.uniform(-np.pi, np.pi, n)  # random headings, like the classic grid data sets
        return np.stack([pos[:, 0], pos[:, 1], np.cos(th), np.sin(th)], -1), pairs
    return np.concatenate([pos, _random_quat(rng, n)], -1), pairs


def synthetic_pose_graph(
    kind: str = "SE3",
    n_poses: int = 200,
    loop_closures: int | None = None,
    noise: Sequence[float] = (0.01, 0.05),
    seed: int = 0,
    shape: str | None = None,
) -> tuple[PoseGraph, np.ndarray]:
    """A noisy pose graph with odometry edges and loop closures, and its ground truth.

    Shapes (``None``: ``"sphere"`` for SE3, ``"circle"`` for SE2):
        * ``"sphere"`` (SE3 only): rings of about √n poses around a sphere, like sphere2500;
          loop closures join each pose to the one at the same longitude on the previous ring.
        * ``"circle"``: laps of about √n poses around a circle (z = 0, yaw only for SE3);
          loop closures join each pose to the same place on the previous lap.
        * ``"grid"``: a boustrophedon walk through a cube (SE3) or square (SE2) with unit
          spacing and random orientations, like smallGrid3D; loop closures join lattice
          neighbours that are not consecutive in time.

    Args:
        kind: ``"SE3"`` or ``"SE2"``.
        n_poses: number of poses n (≥ 2).
        loop_closures: how many loop-closure edges to draw (uniformly, without replacement)
            from the shape's candidates; ``None`` keeps all of them.
        noise: ``(rot_sigma, trans_sigma)`` in radians and length units. Each measurement is
            ``Z = (Xi⁻¹·Xj)·Exp(ξ)`` with ``ξ ~ N(0, Σ)``, ``Σ = diag(σt², …, σr², …)``
            (translation first), so the residual ``Log(Z⁻¹·Xi⁻¹·Xj) = −ξ`` has covariance
            exactly Σ and ``information = Σ⁻¹``; a zero sigma gives information 1 for those
            components (and exact measurements).
        seed: seed of ``numpy.random.default_rng``.

    Returns:
        ``(graph, ground_truth)``: ``graph.poses`` chain the noisy odometry from the true first
        pose (the identity), so the initial guess drifts; ``graph.fixed = [0]``; edges are
        ordered by their later vertex, then their earlier one (loop closures ``(i, k+1)``,
        i < k, before the odometry edge ``(k, k+1)``). ``ground_truth`` is (n, 7) SE3 or
        (n, 4) SE2 storage.
    """
    if kind not in ("SE3", "SE2"):
        raise ValueError(f"synthetic_pose_graph: kind must be 'SE3' or 'SE2', got {kind!r}")
    shape = shape or ("sphere" if kind == "SE3" else "circle")
    if shape not in ("sphere", "grid", "circle"):
        raise ValueError(
            f"synthetic_pose_graph: shape must be 'sphere', 'grid' or 'circle', got {shape!r}"
        )
    if shape == "sphere" and kind == "SE2":
        raise ValueError("synthetic_pose_graph: shape='sphere' needs kind='SE3'")
    if int(n_poses) < 2:
        raise ValueError(f"synthetic_pose_graph: n_poses must be at least 2, got {n_poses}")
    rot_sigma, trans_sigma = (float(v) for v in noise)
    if not (0 <= rot_sigma < np.inf and 0 <= trans_sigma < np.inf):
        raise ValueError(
            f"synthetic_pose_graph: noise sigmas must be finite and >= 0, got {tuple(noise)}"
        )
    n = int(n_poses)
    rng = np.random.default_rng(seed)
    gt, candidates = _trajectory(kind, shape, n, rng)
    gt = compose(kind, inverse(kind, gt[:1]), gt)  # re-anchor: first pose at the identity
    gt[0] = [0, 0, 0, 0, 0, 0, 1] if kind == "SE3" else [0, 0, 1, 0]  # exactly

    if loop_closures is None:
        loops = candidates
    else:
        if not 0 <= int(loop_closures) <= len(candidates):
            raise ValueError(
                f"synthetic_pose_graph: loop_closures={loop_closures}, but shape {shape!r} with "
                f"n_poses={n} has {len(candidates)} candidate pairs"
            )
        pick = np.sort(rng.choice(len(candidates), int(loop_closures), replace=False))
        loops = [candidates[k] for k in pick]
    edges = np.array([(k, k + 1) for k in range(n - 1)] + loops, np.int64).reshape(-1, 2)
    edges = edges[np.lexsort((edges[:, 0], edges[:, 1]))]
    m = len(edges)

    sig = [trans_sigma] * 3 + [rot_sigma] * 3 if kind == "SE3" else [trans_sigma] * 2 + [rot_sigma]
    sig = np.asarray(sig)
    xi = rng.normal(size=(m, len(sig))) * sig
    exp = se3_exp if kind == "SE3" else se2_exp
    relative = compose(kind, inverse(kind, gt[edges[:, 0]]), gt[edges[:, 1]])
    meas = compose(kind, relative, exp(xi))
    weights = np.where(sig > 0, 1.0 / np.where(sig > 0, sig, 1.0) ** 2, 1.0)
    info = np.broadcast_to(np.diag(weights), (m, len(sig), len(sig))).copy()

    odometry = {int(i): e for e, (i, j) in enumerate(edges.tolist()) if j == i + 1}
    chain = [gt[0].tolist()]
    for k in range(n - 1):
        chain.append(compose1(kind, chain[-1], meas[odometry[k]].tolist()))
    poses = np.asarray(chain, np.float64)
    graph = PoseGraph(
        kind=kind,
        vertex_ids=np.arange(n, dtype=np.int64),
        poses=poses,
        edges=edges,
        measurements=meas,
        information=info,
        fixed=np.zeros(1, np.int64),
    )
    return graph, gt


def corrupt_loop_closures(
    graph: PoseGraph, fraction: float, seed: int = 0
) -> tuple[PoseGraph, np.ndarray]:
    """Replace a fraction of a pose graph's loop closures by random (outlier) edges.

    Loop closures are the edges that do not join consecutive poses (``|i − j| ≠ 1``).
    ``round(fraction · count)`` of them, drawn without replacement, are replaced by an edge
    between two random non-consecutive poses with a random measurement: a uniformly random
    rotation (a random yaw for SE2) and a translation uniform in the box spanned by the
    graph's initial poses (at least ±1 per axis); the edge keeps the replaced edge's
    information matrix. Seeded (``numpy.random.default_rng(seed)``).

    Returns:
        ``(graph, outliers)``: the corrupted copy (same edge count and order) and the sorted
        indices of the replaced edges.
    """
    if not 0.0 <= float(fraction) <= 1.0:
        raise ValueError(f"corrupt_loop_closures(fraction={fraction!r}): expected 0 ≤ f ≤ 1")
    n = graph.n_poses
    if n < 3:
        raise ValueError(f"corrupt_loop_closures(graph): needs at least 3 poses, got {n}")
    rng = np.random.default_rng(seed)
    edges = graph.edges.copy()
    loops = np.flatnonzero(np.abs(edges[:, 1] - edges[:, 0]) != 1)
    count = int(round(float(fraction) * loops.size))
    out = np.sort(rng.choice(loops, count, replace=False)) if count else np.zeros(0, np.int64)
    i = rng.integers(0, n, count)
    if n > 3:
        j = (i + rng.integers(2, n - 1, count)) % n  # never i or i ± 1
    else:  # three poses: (0, 2) is the only non-consecutive pair ((i + 2) % 3 is i − 1)
        i = 2 * (i % 2)
        j = 2 - i
    edges[out] = np.stack([i, j], 1)
    meas = graph.measurements.copy()
    dim = 3 if graph.kind == "SE3" else 2
    pos = graph.poses[:, :dim]
    half = np.maximum(0.5 * (pos.max(0) - pos.min(0)), 1.0)
    trans = rng.uniform(-half, half, (count, dim))
    if graph.kind == "SE3":
        meas[out] = np.concatenate([trans, _random_quat(rng, count)], 1)
    else:
        yaw = rng.uniform(-np.pi, np.pi, count)
        meas[out] = np.concatenate([trans, np.cos(yaw)[:, None], np.sin(yaw)[:, None]], 1)
    corrupted = PoseGraph(
        kind=graph.kind,
        vertex_ids=graph.vertex_ids,
        poses=graph.poses,
        edges=edges,
        measurements=meas,
        information=graph.information,
        path=None,
        fixed=graph.fixed,
    )
    return corrupted, out


# ----------------------------------------------------------------------------- BAL


def synthetic_bal(
    n_cameras: int = 50,
    n_points: int = 10000,
    obs_per_point: int = 5,
    pixel_noise: float = 1.0,
    seed: int = 0,
    *,
    init_noise: Sequence[float] = (0.01, 0.05, 0.05),
) -> tuple[BALProblem, BALProblem]:
    """A synthetic bundle-adjustment problem in BAL conventions, and its ground truth.

    Scene: points uniform in the unit ball; cameras on a ring of radius 4 around it (heights
    uniform in [−0.5, 0.5]), each looking at a point near the origin, so every point is in
    front of every camera (``P_z`` about −3 or below in BAL's convention) at ``‖p‖ ≲ 0.35``.
    Intrinsics: ``f ~ U(720, 880)``, ``k1 ~ U(−0.1, 0.1)``, ``k2 ~ U(−0.01, 0.01)``. Each
    point is seen by ``obs_per_point`` consecutive cameras on the ring (random start), as
    in a video; observations are ordered by point, then camera, like the BAL files.

    Args:
        n_cameras, n_points: problem size.
        obs_per_point: cameras per point (≤ n_cameras).
        pixel_noise: standard deviation (pixels) of the Gaussian noise on each coordinate.
        seed: seed of ``numpy.random.default_rng``.
        init_noise: ``(rot_sigma, trans_sigma, point_sigma)`` of the initial guess: each
            camera rotation is perturbed by ``Exp(δ)``, δ ~ N(0, rot_sigma² I), translations
            and points by Gaussian offsets; intrinsics start at their true values.

    Returns:
        ``(problem, ground_truth)``: both hold the same (noisy) observations and indices;
        ``problem`` has the perturbed cameras and points, ``ground_truth`` the true ones.
    """
    n_cam, n_pt, k = int(n_cameras), int(n_points), int(obs_per_point)
    if n_cam < 1 or n_pt < 1:
        raise ValueError(f"synthetic_bal: need n_cameras, n_points >= 1, got {n_cam}, {n_pt}")
    if not 1 <= k <= n_cam:
        raise ValueError(f"synthetic_bal: obs_per_point must be in [1, {n_cam}], got {k}")
    rot_sigma, trans_sigma, point_sigma = (float(v) for v in init_noise)
    for name, value in (
        ("pixel_noise", float(pixel_noise)),
        ("init_noise[0] (rot_sigma)", rot_sigma),
        ("init_noise[1] (trans_sigma)", trans_sigma),
        ("init_noise[2] (point_sigma)", point_sigma),
    ):
        if not 0 <= value < np.inf:
            raise ValueError(f"synthetic_bal: {name} must be finite and >= 0, got {value}")
    rng = np.random.default_rng(seed)

    # points: uniform in the unit ball
    d = rng.normal(size=(n_pt, 3))
    points = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(size=(n_pt, 1)) ** (1 / 3)

    # cameras: centres on a ring, optical axis (−z_cam) towards a target near the origin
    az = 2 * np.pi * np.arange(n_cam) / n_cam
    centres = np.stack([4 * np.cos(az), 4 * np.sin(az), rng.uniform(-0.5, 0.5, n_cam)], -1)
    target = rng.normal(scale=0.1, size=(n_cam, 3))
    forward = target - centres
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    z_cam = -forward
    y_cam = np.cross(z_cam, right)
    R = np.stack([right, y_cam, z_cam], 1)  # rows: camera axes in world coordinates
    t = -np.einsum("nij,nj->ni", R, centres)
    intr = np.stack(
        [
            rng.uniform(720, 880, n_cam),
            rng.uniform(-0.1, 0.1, n_cam),
            rng.uniform(-0.01, 0.01, n_cam),
        ],
        -1,
    )
    quat = quat_from_matrix(R)
    cameras = np.concatenate([rotvec_from_quat(quat), t, intr], -1)

    # observations: consecutive cameras on the ring, sorted by point then camera
    start = rng.integers(0, n_cam, n_pt)
    cam_idx = np.sort((start[:, None] + np.arange(k)) % n_cam, axis=1).reshape(-1)
    pt_idx = np.repeat(np.arange(n_pt, dtype=np.int64), k)
    obs = _bal_project_numpy(cameras, points, cam_idx, pt_idx)
    obs = obs + rng.normal(scale=float(pixel_noise), size=obs.shape)
    truth = BALProblem(cameras, points, cam_idx, pt_idx, obs)

    # initial guess
    dq = so3_exp(rng.normal(scale=rot_sigma, size=(n_cam, 3)))
    init_rot = rotvec_from_quat(quat_mul(dq, quat))
    init_t = t + rng.normal(scale=trans_sigma, size=t.shape)
    init_cams = np.concatenate([init_rot, init_t, intr], -1)
    init_pts = points + rng.normal(scale=point_sigma, size=points.shape)
    return BALProblem(init_cams, init_pts, cam_idx, pt_idx, obs), truth
