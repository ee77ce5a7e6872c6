"""Shared helpers for the I/O and synthetic-data tests (imported as ``io_refs``: tests/io is not
a package, because a package named ``io`` would shadow the standard library).

* ``data_file(...)``: a path under ``../shared/data`` (next to the repository root); the test
  is skipped with a clear reason when the reference data are not there.
* Independent numpy references (no code from ``jaxpose``): ``quat_matrix`` (explicit
  quaternion-to-matrix formula), ``pose_matrix`` (storage → homogeneous matrix),
  ``rodrigues_matrix`` (Rodrigues' formula as a matrix), ``bal_project``.
* ``write_text(tmp_path, lines)``: a small file from a list of lines.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def data_file(*parts: str) -> Path:
    path = DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"reference data {path} not found (expected ../shared/data beside the repo)")
    return path


def write_text(tmp_path: Path, lines: list[str], name: str = "bad.g2o") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def quat_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) [x, y, z, w] (normalised here) -> (..., 3, 3)."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def pose_matrix(kind: str, p: np.ndarray) -> np.ndarray:
    """(..., 7) SE3 or (..., 4) SE2 storage -> (..., 4, 4) or (..., 3, 3) homogeneous."""
    p = np.asarray(p, np.float64)
    if kind == "SE3":
        M = np.zeros(p.shape[:-1] + (4, 4))
        M[..., :3, :3] = quat_matrix(p[..., 3:])
        M[..., :3, 3] = p[..., :3]
    else:
        th = np.arctan2(p[..., 3], p[..., 2])
        M = np.zeros(p.shape[:-1] + (3, 3))
        M[..., 0, 0], M[..., 0, 1] = np.cos(th), -np.sin(th)
        M[..., 1, 0], M[..., 1, 1] = np.sin(th), np.cos(th)
        M[..., :2, 2] = p[..., :2]
    M[..., -1, -1] = 1.0
    return M


def relative_matrix(kind: str, poses: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Xi⁻¹·Xj as matrices for each edge (i, j)."""
    M = pose_matrix(kind, poses)
    return np.linalg.inv(M[edges[:, 0]]) @ M[edges[:, 1]]


def rodrigues_matrix(r: np.ndarray) -> np.ndarray:
    """(..., 3) angle-axis -> (..., 3, 3) by R = I + sinθ K + (1 − cosθ) K², K = [k]×."""
    th = np.linalg.norm(r, axis=-1)[..., None, None]
    k = r / np.where(th[..., 0] > 0, th[..., 0], 1.0)
    K = np.zeros(r.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -k[..., 2], k[..., 1]
    K[..., 1, 0], K[..., 1, 2] = k[..., 2], -k[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -k[..., 1], k[..., 0]
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * (K @ K)


def bal_project(cameras: np.ndarray, points: np.ndarray, cam: np.ndarray, pt: np.ndarray):
    """Independent BAL projection: returns (pixels (n_obs, 2), camera-frame P (n_obs, 3))."""
    c = cameras[cam]
    P = np.einsum("nij,nj->ni", rodrigues_matrix(c[:, :3]), points[pt]) + c[:, 3:6]
    x, y = -P[:, 0] / P[:, 2], -P[:, 1] / P[:, 2]
    r2 = x * x + y * y
    scale = c[:, 6] * (1 + c[:, 7] * r2 + c[:, 8] * r2 * r2)
    return np.stack([scale * x, scale * y], -1), P


def log_matrix(kind: str, M: np.ndarray) -> np.ndarray:
    """Log of (..., 4, 4) SE3 / (..., 3, 3) SE2 matrices with rotation angles well below π:
    se3 ``[ρ, φ]`` with ``t = Jl(φ)·ρ``; se2 ``[ρx, ρy, θ]`` with ``t = V(θ)·ρ``."""
    if kind == "SE2":
        th = np.arctan2(M[..., 1, 0], M[..., 0, 0])
        a, b = np.sinc(th / np.pi), th / 2 * np.sinc(th / (2 * np.pi)) ** 2  # sinθ/θ, (1−cosθ)/θ
        V = np.stack([np.stack([a, -b], -1), np.stack([b, a], -1)], -2)
        rho = np.linalg.solve(V, M[..., :2, 2:])[..., 0]
        return np.concatenate([rho, th[..., None]], -1)
    R, t = M[..., :3, :3], M[..., :3, 3]
    th = np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1))
    w = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    phi = w / (2 * np.sinc(th / np.pi))[..., None]
    K = np.zeros(R.shape)
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -phi[..., 2], phi[..., 1], -phi[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    th2 = (th * th)[..., None, None]
    a = np.where(th2 < 1e-8, 0.5, (1 - np.cos(np.sqrt(th2))) / np.where(th2 < 1e-8, 1, th2))
    s = np.sqrt(np.where(th2 < 1e-8, 1, th2))
    b = np.where(th2 < 1e-8, 1 / 6, (s - np.sin(s)) / (s * s * s))
    Jl = np.eye(3) + a * K + b * (K @ K)
    return np.concatenate([np.linalg.solve(Jl, t[..., None])[..., 0], phi], -1)
