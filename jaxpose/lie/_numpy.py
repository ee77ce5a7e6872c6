"""Float64 NumPy Lie-group helpers for host code (readers, data generators, initialisers).

Storage as in :mod:`jaxpose.lie`: quaternions ``[x, y, z, w]``; SE3 ``[t (3), q (4)]``
(..., 7); SE2 ``[x, y, cos θ, sin θ]`` (..., 4). NumPy, not JAX: file readers and data
generators run before any device is involved and must not depend on ``jax_enable_x64``.
Internal: used by :mod:`jaxpose.io`, :mod:`jaxpose.datasets`, :mod:`jaxpose.graph.init`
and the CLI.
"""

from __future__ import annotations

import math

import numpy as np


def normalize(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` (..., k) scaled to unit norm without overflow or underflow: divided by
    their largest magnitude first (‖v‖ of a 1e200 quaternion is inf, of a 1e-200 one is 0)."""
    scale = np.max(np.abs(v), axis=-1, keepdims=True)
    u = v / np.where(scale > 0, scale, 1.0)
    return u / np.linalg.norm(u, axis=-1, keepdims=True)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) ``[x, y, z, w]`` quaternions."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        -1,
    )


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate (..., 3) vectors by unit (..., 4) quaternions."""
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (inverse of a unit quaternion) of (..., 4) ``[x, y, z, w]``."""
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def compose(kind: str, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a · b`` for (..., 7) SE3 or (..., 4) SE2 storage."""
    if kind == "SE3":
        q = normalize(quat_mul(a[..., 3:], b[..., 3:]))
        return np.concatenate([a[..., :3] + quat_rotate(a[..., 3:], b[..., :3]), q], -1)
    c, s = a[..., 2], a[..., 3]
    bx, by = b[..., 0], b[..., 1]
    cs = np.stack([c * b[..., 2] - s * b[..., 3], s * b[..., 2] + c * b[..., 3]], -1)
    cs = normalize(cs)
    t = np.stack([a[..., 0] + c * bx - s * by, a[..., 1] + s * bx + c * by], -1)
    return np.concatenate([t, cs], -1)


def inverse(kind: str, x: np.ndarray) -> np.ndarray:
    """``x⁻¹`` for (..., 7) SE3 or (..., 4) SE2 storage."""
    if kind == "SE3":
        qc = quat_conj(x[..., 3:])
        return np.concatenate([-quat_rotate(qc, x[..., :3]), qc], -1)
    c, s, tx, ty = x[..., 2], x[..., 3], x[..., 0], x[..., 1]
    return np.stack([-(c * tx + s * ty), s * tx - c * ty, c, -s], -1)


def compose1(kind: str, a: list[float], b: list[float]) -> list[float]:
    """``a · b`` for one pose as plain floats (the sequential chaining loops; ~100x faster
    than numpy on single poses)."""
    if kind == "SE3":
        ax, ay, az, aw = a[3:]
        bx, by, bz, bw = b[3:]
        qx = aw * bx + ax * bw + ay * bz - az * by
        qy = aw * by - ax * bz + ay * bw + az * bx
        qz = aw * bz + ax * by - ay * bx + az * bw
        qw = aw * bw - ax * bx - ay * by - az * bz
        n = math.hypot(qx, qy, qz, qw)  # scale-safe; ≈ 1 for the unit quaternions read
        vx, vy, vz = b[:3]  # rotate b's translation by a's rotation: v + w·t + u × t
        tx, ty, tz = 2 * (ay * vz - az * vy), 2 * (az * vx - ax * vz), 2 * (ax * vy - ay * vx)
        return [
            a[0] + vx + aw * tx + (ay * tz - az * ty),
            a[1] + vy + aw * ty + (az * tx - ax * tz),
            a[2] + vz + aw * tz + (ax * ty - ay * tx),
            qx / n,
            qy / n,
            qz / n,
            qw / n,
        ]
    c, s = a[2], a[3]
    cc, ss = c * b[2] - s * b[3], s * b[2] + c * b[3]
    n = math.hypot(cc, ss)
    return [a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], cc / n, ss / n]


def identity(kind: str) -> np.ndarray:
    """Identity pose storage: (7,) SE3 or (4,) SE2."""
    return np.array([0, 0, 0, 0, 0, 0, 1.0]) if kind == "SE3" else np.array([0, 0, 1.0, 0])


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 4) unit quaternions ``[x, y, z, w]``."""
    theta2 = np.sum(phi * phi, -1, keepdims=True)
    theta = np.sqrt(theta2)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    # sin(θ/2)/θ; series 1/2 − θ²/48 + θ⁴/3840 is exact to float64 below 1e-4
    half_sinc = np.where(small, 0.5 - theta2 / 48 + theta2**2 / 3840, np.sin(safe / 2) / safe)
    return np.concatenate([phi * half_sinc, np.cos(theta / 2)], -1)


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) vectors → (..., 3, 3) skew-symmetric matrices ``[v]×``."""
    z = np.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """(..., 6) ``[ρ, φ]`` -> (..., 7) SE3 storage: ``(Jl(φ)·ρ, Exp(φ))``."""
    rho, phi = xi[..., :3], xi[..., 3:]
    t2 = np.sum(phi * phi, -1)[..., None, None]
    small = t2 < 1e-2  # θ < 0.1: the series below is exact to float64 precision
    s = np.where(small, 1.0, t2)
    th = np.sqrt(s)
    a_series = 0.5 - t2 / 24 + t2**2 / 720 - t2**3 / 40320 + t2**4 / 3628800
    b_series = 1 / 6 - t2 / 120 + t2**2 / 5040 - t2**3 / 362880 + t2**4 / 39916800
    a = np.where(small, a_series, 2 * np.sin(th / 2) ** 2 / s)  # (1 − cos θ)/θ²
    b = np.where(small, b_series, (th - np.sin(th)) / (s * th))  # (θ − sin θ)/θ³
    K = skew(phi)
    Jl = np.eye(3) + a * K + b * (K @ K)
    return np.concatenate([(Jl @ rho[..., None])[..., 0], so3_exp(phi)], -1)


def se2_exp(xi: np.ndarray) -> np.ndarray:
    """(..., 3) ``[ρx, ρy, θ]`` -> (..., 4) SE2 storage: ``(V(θ)·ρ, cos θ, sin θ)``."""
    th = xi[..., 2]
    small = np.abs(th) < 1e-4
    safe = np.where(small, 1.0, th)
    a = np.where(small, 1 - th**2 / 6 + th**4 / 120, np.sin(safe) / safe)
    b = np.where(small, th / 2 - th**3 / 24 + th**5 / 720, 2 * np.sin(safe / 2) ** 2 / safe)
    x, y = xi[..., 0], xi[..., 1]
    return np.stack([a * x - b * y, b * x + a * y, np.cos(th), np.sin(th)], -1)


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions ``[x, y, z, w]``, w ≥ 0."""
    m = lambda i, j: R[..., i, j]
    tr = m(0, 0) + m(1, 1) + m(2, 2)
    # Shepperd: four unnormalised candidates; keep the one with the largest pivot
    cands = np.stack(
        [
            [m(2, 1) - m(1, 2), m(0, 2) - m(2, 0), m(1, 0) - m(0, 1), 1 + tr],
            [1 + 2 * m(0, 0) - tr, m(0, 1) + m(1, 0), m(0, 2) + m(2, 0), m(2, 1) - m(1, 2)],
            [m(0, 1) + m(1, 0), 1 + 2 * m(1, 1) - tr, m(1, 2) + m(2, 1), m(0, 2) - m(2, 0)],
            [m(0, 2) + m(2, 0), m(1, 2) + m(2, 1), 1 + 2 * m(2, 2) - tr, m(1, 0) - m(0, 1)],
        ]
    )  # (4 candidates, 4 components, ...)
    pivots = np.stack([1 + tr, *(1 + 2 * m(k, k) - tr for k in range(3))])
    best = np.argmax(pivots, 0)
    q = np.moveaxis(np.take_along_axis(cands, best[None, None], 0)[0], 0, -1)
    q = normalize(q)
    return q * np.where(q[..., 3:] < 0, -1.0, 1.0)


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions -> (..., 3) rotation vectors with angle in [0, π]."""
    q = q * np.where(q[..., 3:] < 0, -1.0, 1.0)
    v, w = q[..., :3], q[..., 3:]
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    small = n < 1e-8
    safe = np.where(small, 1.0, n)
    return v * np.where(small, 2.0 / w, 2 * np.arctan2(n, w) / safe)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) ``[x, y, z, w]`` quaternions, normalised
    first (:func:`normalize`: a quaternion scaled by 1e-200 is one too)."""
    q = normalize(q)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - z * w),
            2 * (x * z + y * w),
            2 * (x * y + z * w),
            1 - 2 * (x * x + z * z),
            2 * (y * z - x * w),
            2 * (x * z - y * w),
            2 * (y * z + x * w),
            1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)


def so3_log(r: np.ndarray) -> np.ndarray:
    """Rotation vectors φ (|φ| ≤ π) of (..., 3, 3) rotation matrices, via the quaternion."""
    return rotvec_from_quat(quat_from_matrix(r))


def rodrigues_rotate(r: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Rotate (..., 3) points by (..., 3) Rodrigues (angle-axis) vectors ``r``."""
    theta2 = np.sum(r * r, -1, keepdims=True)
    small = theta2 < 1e-30
    theta = np.sqrt(np.where(small, 1.0, theta2))
    k = r / theta
    c, s = np.cos(theta), np.sin(theta)
    full = X * c + np.cross(k, X) * s + k * np.sum(k * X, -1, keepdims=True) * (1.0 - c)
    return np.where(small, X + np.cross(r, X), full)
