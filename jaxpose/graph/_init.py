"""Global initialisation of SE(2)/SE(3) pose graphs: the chordal relaxation.

Carlone, Tron, Daniilidis, Dellaert, "Initialization techniques for 3D SLAM: a survey on
rotation estimation and its use in pose graph optimization", ICRA 2015:

1. **Rotations.** Relax ``R_j = R_i·Z_ij`` to a linear least-squares problem over the
   entries of the rotation matrices (``‖(R_j − R_i·Z_ij)·W_ij‖²_F`` summed over the edges),
   with one pose per connected piece held at its current value (the gauge anchors of
   :func:`gauge_anchors`, the poses LM then holds fixed); project every
   3×3 (2×2) block to SO(3) (SO(2)) by SVD.
2. **Translations.** With the rotations fixed, the translation part of the residual
   ``Log(Z⁻¹·Xi⁻¹·Xj)`` is linear in the translations, ``V(φ)⁻¹·Z_Rᵀ·(R_iᵀ(t_j − t_i) − t_z)``,
   so the full cost ``½Σ rᵀΩr`` (φ fixed) is minimised exactly by one linear least-squares
   solve.

Full information matrices are used, no diagonal assumption. For small errors
``R_j = R_i·Z·Exp(φ)``, ``‖(R_j − R_i Z)·W‖²_F = φᵀ(tr(M)·I − M)φ`` with ``M = W·Wᵀ``, so
the rotational block Ω_R of each edge is reproduced exactly by ``M = ½tr(Ω_R)·I − Ω_R``
(clipped to positive semi-definite when Ω_R is so anisotropic that its largest eigenvalue
exceeds half its trace). In 2D the weight is ``Ω_θθ`` on ``|(c_j + i s_j) − (c_i + i s_i)
(c_z + i s_z)|²``. In the translation step the translational block weights the rows and
the cross block Ω_tR shifts their target to ``−Ω_tt⁻¹·Ω_tR·φ`` (the minimiser of the full
quadratic form over the translation residual).

Where it runs: on the host, in NumPy and SciPy (sparse assembly of the normal equations
``AᵀA``) and CHOLMOD (:mod:`jaxpose.graph._cholmod`, one factorisation per linear system;
SciPy's sparse solver when CHOLMOD is unavailable); systems of at most ``_DENSE_MAX``
unknowns densely in NumPy (dense Cholesky). The whole initialisation takes tens of
milliseconds on the shared graphs (sphere_bignoise_vertex3: 2200 poses, 8647 edges), less
than tracing a jitted version would, so it is not jitted; it is not differentiable either
(use it to produce a starting point, then :func:`jaxpose.graph.solve`).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse

from ..io._g2o import connected_components
from ..lie._numpy import quat_from_matrix, quat_to_matrix, skew, so3_log
from . import _cholmod as cholmod

__all__ = ["INIT_METHODS", "chordal_initialization", "initial_poses", "pose_graph_cost"]


def _project_so(m: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius) to each (..., n, n) matrix, by SVD."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    d = np.where(d == 0, 1.0, d)
    u = u.copy()
    u[..., :, -1] *= d[..., None]
    return u @ vt


def _psd_parts(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, M⁺)`` for each (m, k, k) symmetric positive semi-definite ``M``: a square root
    ``RᵀR = M`` (negative eigenvalues clipped to zero) and the pseudo-inverse (eigenvalues
    at most 1e-15 of the largest count as zero, as ``np.linalg.pinv(hermitian=True)``).

    Diagonal matrices (most files' information blocks) take square roots and reciprocals
    of the diagonal; the others Cholesky (``R = Lᵀ``) when every pivot is above 1e-12 of
    the largest diagonal entry, else an eigendecomposition (``R`` symmetric)."""
    m = 0.5 * (m + np.swapaxes(m, -1, -2))
    eye = np.eye(m.shape[-1])

    def parts(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        big = np.abs(w) > 1e-15 * np.max(np.abs(w), axis=-1, keepdims=True)
        return np.sqrt(np.clip(w, 0.0, None)), np.where(big, 1.0 / np.where(big, w, 1.0), 0.0)

    d = np.diagonal(m, axis1=-2, axis2=-1)
    root, pinv = (eye * x[..., None, :] for x in parts(d))
    full = ~np.all(m == eye * d[..., None, :], axis=(-2, -1))
    # Cholesky pivots are ratios of leading principal minors
    minors = np.stack([np.ones(m.shape[0])]
                      + [np.linalg.det(m[:, :s, :s]) for s in range(1, m.shape[-1] + 1)], -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        pivots = minors[:, 1:] / minors[:, :-1]
    tol = 1e-12 * np.max(np.abs(d), -1, keepdims=True)
    chol = full & np.all(minors[:, :-1] > 0, -1) & np.all(pivots > tol, -1)
    eig = full & ~chol
    if np.any(chol):
        lower = np.linalg.cholesky(m[chol])
        lower_inv = np.linalg.inv(lower)
        root[chol] = np.swapaxes(lower, -1, -2)
        pinv[chol] = np.swapaxes(lower_inv, -1, -2) @ lower_inv
    if np.any(eig):
        w, v = np.linalg.eigh(m[eig])
        vt = np.swapaxes(v, -1, -2)
        sq, inv = parts(w)
        root[eig] = (v * sq[..., None, :]) @ vt
        pinv[eig] = (v * inv[..., None, :]) @ vt
    return root, pinv


def _v_inverse(phi: np.ndarray) -> np.ndarray:
    """V(φ)⁻¹ of the SE(3) logarithm (translation part ``V⁻¹·t``), (m, 3) → (m, 3, 3)."""
    th2 = np.sum(phi * phi, -1)
    th = np.sqrt(th2)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    coef = np.where(
        small,
        1.0 / 12.0 + th2 / 720.0,
        (1.0 - ths * np.sin(ths) / (2.0 * np.where(small, 1.0, 1.0 - np.cos(ths)))) / ths**2,
    )
    w = skew(phi)
    return np.eye(3) - 0.5 * w + coef[:, None, None] * (w @ w)


def _v2_inverse(th: np.ndarray) -> np.ndarray:
    """V(θ)⁻¹ of the SE(2) logarithm, (m,) → (m, 2, 2)."""
    small = np.abs(th) < 1e-6
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, th / 2.0, (1.0 - np.cos(ths)) / ths)
    det = a * a + b * b
    return np.stack([a, b, -b, a], -1).reshape(-1, 2, 2) / det[:, None, None]


def _spd_solve(h: scipy.sparse.csr_matrix, rhs: np.ndarray) -> np.ndarray:
    """Solve H X = RHS (H sparse SPD, RHS (N, p)) with CHOLMOD (SciPy when CHOLMOD is
    unavailable); non-finite values when H is singular."""
    h = h.tocsr()
    h.sum_duplicates()
    h.sort_indices()
    if cholmod.available():
        return cholmod.solve(h.data, h.indices, h.indptr, rhs)  # NaN when not SPD
    import scipy.sparse.linalg

    with warnings.catch_warnings():  # singular: non-finite values, which the caller handles
        warnings.simplefilter("ignore", scipy.sparse.linalg.MatrixRankWarning)
        return np.asarray(scipy.sparse.linalg.spsolve(h.tocsc(), rhs)).reshape(rhs.shape)


_DENSE_MAX = 64
"""Unknowns up to which :func:`_block_lstsq` solves densely in NumPy, where SciPy's sparse
assembly and the CHOLMOD call cost more than the arithmetic: measured (random 9×3 blocks,
two edges per vertex) 0.13 against 0.44 ms at 12 unknowns, 0.18 against 0.48 ms at 30,
even at 81 (0.63 / 0.59 ms) and 5.4 against 0.9 ms at 252."""


def _sparse_lstsq(vals: np.ndarray, r: np.ndarray, cc: np.ndarray, shape: tuple[int, int],
                  rhs_rows: np.ndarray) -> np.ndarray:
    """Least-squares X of ``A X = C``, A sparse from COO ``(vals, (r, cc))`` of ``shape``,
    through the normal equations AᵀA (CHOLMOD); a 1e-12 ridge where they are singular."""
    a = scipy.sparse.csr_matrix((vals, (r, cc)), shape=shape)
    h = (a.T @ a).tocsr()
    rhs = np.asarray(a.T @ rhs_rows)
    x = _spd_solve(h, rhs)
    if not np.all(np.isfinite(x)):  # a free vertex seen only by zero-weight edges
        x = _spd_solve(h + scipy.sparse.diags(np.full(h.shape[0], _ridge(h.diagonal()))), rhs)
    return x


def _dense_lstsq(vals: np.ndarray, r: np.ndarray, cc: np.ndarray, shape: tuple[int, int],
                 rhs_rows: np.ndarray) -> np.ndarray:
    """:func:`_sparse_lstsq` with A dense (small systems): Cholesky of AᵀA, the same
    ridge where it is not positive definite."""
    a = np.zeros(shape)
    np.add.at(a, (r, cc), vals)
    h = a.T @ a
    rhs = a.T @ rhs_rows
    for ridge in (0.0, _ridge(np.diagonal(h))):
        try:
            low = np.linalg.cholesky(h + ridge * np.eye(h.shape[0]))
        except np.linalg.LinAlgError:
            continue
        return scipy.linalg.cho_solve((low, True), rhs, check_finite=False)
    return np.full(rhs.shape, np.nan)


def _ridge(diag: np.ndarray) -> float:
    return 1e-12 * (float(diag.max()) if diag.size and diag.max() > 0 else 1.0)


def _block_lstsq(
    n: int,
    edges: np.ndarray,
    bi: np.ndarray,
    bj: np.ndarray,
    c: np.ndarray,
    anchors: np.ndarray,
    x_anchor: np.ndarray,
) -> np.ndarray:
    """Least-squares solution of ``Bj_e·X_j + Bi_e·X_i = C_e`` for every edge e.

    bi, bj: (m, k, d); c: (m, k, p); unknowns X_v (d, p) for every vertex; the vertices in
    ``anchors`` are held at ``x_anchor`` (len(anchors), d, p). Returns X (n, d, p)."""
    m, k, d = bi.shape
    p = c.shape[-1]
    held = np.zeros(n, bool)
    held[anchors] = True
    x_all = np.zeros((n, d, p))
    x_all[anchors] = x_anchor
    i, j = edges[:, 0], edges[:, 1]
    # move the anchored unknowns to the right-hand side
    c = c - np.where(held[i][:, None, None], bi @ x_all[i], 0.0)
    c = c - np.where(held[j][:, None, None], bj @ x_all[j], 0.0)
    free = np.flatnonzero(~held)
    col = np.full(n, -1)
    col[free] = np.arange(free.size)
    rows = np.arange(m)[:, None] * k + np.arange(k)[None, :]  # (m, k)
    entries = []
    for ends, blocks in ((i, bi), (j, bj)):
        keep = col[ends] >= 0
        r = np.broadcast_to(rows[keep][:, :, None], (int(keep.sum()), k, d))
        cc = col[ends][keep][:, None, None] * d + np.arange(d)[None, None, :]
        cc = np.broadcast_to(cc, r.shape)
        entries.append((blocks[keep].reshape(-1), r.reshape(-1), cc.reshape(-1)))
    vals, r, cc = (np.concatenate(a) for a in zip(*entries, strict=True))
    lstsq = _dense_lstsq if free.size * d <= _DENSE_MAX else _sparse_lstsq
    x = lstsq(vals, r, cc, (m * k, free.size * d), c.reshape(m * k, p))
    x_all[free] = x.reshape(free.size, d, p)
    return x_all


def gauge_anchors(graph: Any, held: Any) -> np.ndarray:
    """Sorted indices to hold constant: ``held`` plus the first pose of every connected
    piece of ``graph`` that contains none of them."""
    held = np.unique(np.asarray(held, np.int64).reshape(-1))
    if graph.n_poses == 0:
        return held
    labels = connected_components(graph)
    firsts = np.unique(labels, return_index=True)[1]
    free_pieces = np.setdiff1d(np.arange(firsts.size), labels[held])
    return np.union1d(held, firsts[free_pieces])


def _anchors(graph: Any, fix: str) -> np.ndarray:
    if fix not in ("first", "file", "none"):
        raise ValueError(f"chordal_initialization(fix={fix!r}): expected 'first', 'file' or 'none'")
    file_fixed = np.asarray(getattr(graph, "fixed", []), dtype=np.int64)
    held = file_fixed if (fix == "file" and file_fixed.size) else np.zeros(1, np.int64)
    return gauge_anchors(graph, held)


def chordal_initialization(graph: Any, *, fix: str = "first") -> np.ndarray:
    """Chordal-relaxation initial poses of a :class:`~jaxpose.io.PoseGraph` (SE3 or SE2).

    Args:
        graph: the pose graph (``kind``, ``poses``, ``edges``, ``measurements``,
            ``information``). Only the anchored poses' values are used, so edge-only files
            (whose ``poses`` the reader chains from the odometry) work as well.
        fix: which poses anchor the gauge, as in
            :func:`~jaxpose.graph.pose_graph_problem`: ``"first"`` (pose 0 plus the
            first pose of every further disconnected piece), ``"file"`` (the graph's FIX
            vertices) or ``"none"`` (treated as ``"first"``: the relaxation needs an anchor).

    Returns:
        (n, 7) SE3 ``[t, q]`` or (n, 4) SE2 ``[t, cos, sin]`` float64 poses; the anchored
        poses are returned unchanged. Runs on the host (module docstring).
    """
    if graph.kind not in ("SE3", "SE2"):
        raise ValueError(f"chordal_initialization(graph): unsupported kind {graph.kind!r}")
    poses = np.asarray(graph.poses, np.float64)
    n = poses.shape[0]
    if n == 0:
        return poses.copy()
    anchors = _anchors(graph, "first" if fix == "none" else fix)
    edges = np.asarray(graph.edges, np.int64).reshape(-1, 2)
    z = np.asarray(graph.measurements, np.float64)
    info = np.asarray(graph.information, np.float64)
    info = 0.5 * (info + np.swapaxes(info, -1, -2))
    m = edges.shape[0]
    i, j = edges[:, 0], edges[:, 1]
    if m == 0:
        return poses.copy()
    if graph.kind == "SE3":
        return _chordal_se3(poses, edges, z, info, anchors, i, j)
    return _chordal_se2(poses, edges, z, info, anchors, i, j)


def _translations(
    n: int,
    edges: np.ndarray,
    rot: np.ndarray,
    zr: np.ndarray,
    zt: np.ndarray,
    info: np.ndarray,
    phi: np.ndarray,
    vinv: np.ndarray,
    anchors: np.ndarray,
    t_anchor: np.ndarray,
) -> np.ndarray:
    """Translations minimising ½Σ rᵀΩr with the rotations (and so φ) fixed."""
    dt = zt.shape[-1]
    i = edges[:, 0]
    o_tt, o_tr = info[:, :dt, :dt], info[:, :dt, dt:]
    s, o_tt_pinv = _psd_parts(o_tt)
    # target of the translation residual: −Ω_tt⁻¹·Ω_tR·φ (pinv: Ω_tt may be singular)
    target = -np.einsum(
        "mij,mj->mi",
        o_tt_pinv,
        np.einsum("mij,mj->mi", o_tr, phi.reshape(len(i), -1)),
    )
    a = vinv @ np.swapaxes(zr, -1, -2)  # V⁻¹·Z_Rᵀ
    bj = s @ a @ np.swapaxes(rot[i], -1, -2)
    c = np.einsum("mij,mj->mi", s, target + np.einsum("mij,mj->mi", a, zt))[..., None]
    x = _block_lstsq(n, edges, -bj, bj, c, anchors, t_anchor[..., None])
    return x[..., 0]


def _chordal_se3(poses, edges, z, info, anchors, i, j) -> np.ndarray:
    n = poses.shape[0]
    zr = quat_to_matrix(z[:, 3:])
    o_rr = info[:, 3:, 3:]
    mm = 0.5 * np.trace(o_rr, axis1=1, axis2=2)[:, None, None] * np.eye(3) - o_rr
    w = _psd_parts(mm)[0]
    # unknowns X_v = R_vᵀ (3×3; its columns are the rows of R_v): W·R_jᵀ − W·Z_ijᵀ·R_iᵀ = 0
    bj = w
    bi = -w @ np.swapaxes(zr, -1, -2)
    c = np.zeros((len(edges), 3, 3))
    r_anchor = quat_to_matrix(poses[anchors, 3:])
    x = _block_lstsq(n, edges, bi, bj, c, anchors, np.swapaxes(r_anchor, -1, -2))
    rot = _project_so(np.swapaxes(x, -1, -2))
    rot[anchors] = r_anchor
    phi = so3_log(np.swapaxes(zr, -1, -2) @ np.swapaxes(rot[i], -1, -2) @ rot[j])
    t = _translations(
        n, edges, rot, zr, z[:, :3], info, phi, _v_inverse(phi), anchors, poses[anchors, :3]
    )
    out = np.concatenate([t, quat_from_matrix(rot)], 1)
    out[anchors] = poses[anchors]
    return out


def _chordal_se2(poses, edges, z, info, anchors, i, j) -> np.ndarray:
    n = poses.shape[0]
    cz, sz = z[:, 2], z[:, 3]
    nz = np.hypot(cz, sz)
    cz, sz = cz / nz, sz / nz
    w = np.sqrt(np.clip(info[:, 2, 2], 0.0, None))[:, None, None]
    # unknowns (c, s) per pose: (c_j + i s_j) − (c_i + i s_i)(c_z + i s_z) = 0, weight √Ω_θθ
    rz = np.stack([cz, -sz, sz, cz], -1).reshape(-1, 2, 2)
    bj = w * np.eye(2)
    bi = -w * rz
    c = np.zeros((len(edges), 2, 1))
    cs_anchor = poses[anchors, 2:4] / np.linalg.norm(poses[anchors, 2:4], axis=1, keepdims=True)
    x = _block_lstsq(n, edges, bi, bj, c, anchors, cs_anchor[..., None])[..., 0]
    norm = np.linalg.norm(x, axis=1)
    x = np.where(norm[:, None] > 0, x / np.where(norm > 0, norm, 1.0)[:, None], [1.0, 0.0])
    x[anchors] = cs_anchor
    rot = np.stack([x[:, 0], -x[:, 1], x[:, 1], x[:, 0]], -1).reshape(-1, 2, 2)
    # θ of Z⁻¹·R_iᵀ·R_j
    th_i, th_j = np.arctan2(x[i, 1], x[i, 0]), np.arctan2(x[j, 1], x[j, 0])
    phi = np.angle(np.exp(1j * (th_j - th_i - np.arctan2(sz, cz))))
    t = _translations(
        n,
        edges,
        rot,
        rz,
        z[:, :2],
        info,
        phi[:, None],
        _v2_inverse(phi),
        anchors,
        poses[anchors, :2],
    )
    out = np.concatenate([t, x], 1)
    out[anchors] = poses[anchors]
    return out


INIT_METHODS = ("auto", "chordal", "odometry")
"""Values of ``init`` in :func:`initial_poses` / ``optimize_pose_graph`` / ``jaxpose pgo``."""


def pose_graph_cost(graph: Any, poses: Any = None) -> float:
    """``0.5·Σ rᵀΩr`` with ``r = Log(Z⁻¹·Xi⁻¹·Xj)`` at ``poses`` (default ``graph.poses``),
    in NumPy float64 on the host (no compilation; used to choose an initialisation)."""
    if poses is not None and np.shape(getattr(poses, "data", poses)) != np.shape(graph.poses):
        raise ValueError(
            f"pose_graph_cost(poses): expected shape {np.shape(graph.poses)} like graph.poses, "
            f"got {np.shape(getattr(poses, 'data', poses))}")
    return _pose_graph_costs(graph, [graph.poses if poses is None else poses])[0]


def _pose_graph_costs(graph: Any, pose_sets: list[Any]) -> list[float]:
    """:func:`pose_graph_cost` of each pose set, in one pass: the sets are stacked as one
    graph of ``len(pose_sets)`` disconnected copies (half the NumPy calls for two)."""
    sets = [np.asarray(getattr(p, "data", p), np.float64) for p in pose_sets]
    edges = np.asarray(graph.edges, np.int64).reshape(-1, 2)
    m, k = edges.shape[0], len(sets)
    if m == 0:
        return [0.0] * k
    n = sets[0].shape[0]
    poses = np.concatenate(sets)
    edges = np.concatenate([edges + c * n for c in range(k)])
    z = np.tile(np.asarray(graph.measurements, np.float64), (k, 1))
    info = np.tile(np.asarray(graph.information, np.float64), (k, 1, 1))
    i, j = edges[:, 0], edges[:, 1]
    if graph.kind == "SE3":
        ri, rj, zr = (quat_to_matrix(q) for q in (poses[i, 3:], poses[j, 3:], z[:, 3:]))
        zrt = np.swapaxes(zr, -1, -2)
        rel = zrt @ np.swapaxes(ri, -1, -2) @ rj
        u = np.einsum(
            "mij,mj->mi", zrt, np.einsum("mji,mj->mi", ri, poses[j, :3] - poses[i, :3]) - z[:, :3]
        )
        phi = so3_log(rel)
        r = np.concatenate([np.einsum("mij,mj->mi", _v_inverse(phi), u), phi], 1)
    else:
        th = lambda p: np.arctan2(p[..., 3], p[..., 2])  # noqa: E731
        ci, si = np.cos(th(poses[i])), np.sin(th(poses[i]))
        cz, sz = np.cos(th(z)), np.sin(th(z))
        dx, dy = poses[j, 0] - poses[i, 0], poses[j, 1] - poses[i, 1]
        lx, ly = ci * dx + si * dy - z[:, 0], -si * dx + ci * dy - z[:, 1]
        u = np.stack([cz * lx + sz * ly, -sz * lx + cz * ly], 1)
        phi = np.angle(np.exp(1j * (th(poses[j]) - th(poses[i]) - th(z))))
        r = np.concatenate([np.einsum("mij,mj->mi", _v2_inverse(phi), u), phi[:, None]], 1)
    per_edge = np.einsum("mi,mij,mj->m", r, info, r).reshape(k, m)
    return [float(0.5 * c) for c in per_edge.sum(1)]


def initial_poses(graph: Any, init: str = "auto", *, fix: str = "first") -> tuple[np.ndarray, str]:
    """Starting poses for LM on a pose graph; returns ``(poses, method used)``.

    ``init``: ``"odometry"`` keeps ``graph.poses`` (the file's vertices, or the odometry
    chain the reader builds for edge-only files); ``"chordal"`` uses
    :func:`chordal_initialization`; ``"auto"`` uses the chordal poses unless the file's
    poses already have a lower cost (:func:`pose_graph_cost`; e.g. a file that holds an
    optimised solution). Measured on every shared graph (docs/graph.md), chordal then LM
    reaches the lower or an equal final cost, and on sphere_bignoise_vertex3 GTSAM's
    chordal optimum (1.494169e6) where LM from odometry stalls at 3.76e6.
    """
    if init not in INIT_METHODS:
        raise ValueError(f"initial_poses(init={init!r}): expected one of {INIT_METHODS}")
    file_poses = np.asarray(graph.poses, np.float64)
    if init == "odometry" or graph.n_edges == 0:
        return file_poses, "odometry"
    chordal = chordal_initialization(graph, fix=fix)
    if init == "chordal":
        return chordal, "chordal"
    c_file, c_chordal = _pose_graph_costs(graph, [file_poses, chordal])
    if np.isfinite(c_chordal) and not c_file < c_chordal:
        return chordal, "chordal"
    return file_poses, "odometry"
