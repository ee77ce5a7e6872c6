"""Independent float64 numpy references for the IMU tests (no jaxpose code):
Forster et al.'s sequential preintegration recurrences (T-RO 2017, Sec. V and the
supplementary material, eqs. A7–A10 and the bias-Jacobian recurrences), strapdown dead
reckoning, and seeded random IMU windows."""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula (rotation matrix)."""
    th = np.linalg.norm(phi)
    k = skew(phi)
    if th < 1e-8:
        return np.eye(3) + k + 0.5 * k @ k
    return np.eye(3) + np.sin(th) / th * k + (1 - np.cos(th)) / th**2 * k @ k


def so3_log(r: np.ndarray) -> np.ndarray:
    c = np.clip((np.trace(r) - 1) / 2, -1.0, 1.0)
    th = np.arccos(c)
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return 0.5 * w if th < 1e-8 else th / (2 * np.sin(th)) * w


def right_jacobian(phi: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(phi)
    k = skew(phi)
    if th < 1e-6:
        return np.eye(3) - 0.5 * k + k @ k / 6.0
    return np.eye(3) - (1 - np.cos(th)) / th**2 * k + (th - np.sin(th)) / th**3 * k @ k


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def preintegrate(gyro, acc, dt, bg=np.zeros(3), ba=np.zeros(3), sg=np.zeros(3),
                 sa=np.zeros(3), si=0.0):
    """Forster's recurrences, one sample at a time. Returns ``(R, v, p, cov, jac)`` with
    cov (9, 9) over ``[δφ, δv, δp]`` and jac (9, 6) = ∂[φ, v, p]/∂[b_g, b_a]."""
    n = len(dt)
    sg, sa = np.broadcast_to(sg, 3), np.broadcast_to(sa, 3)
    R, v, p = np.eye(3), np.zeros(3), np.zeros(3)
    cov = np.zeros((9, 9))
    dR_bg = np.zeros((3, 3))
    dv_bg, dv_ba = np.zeros((3, 3)), np.zeros((3, 3))
    dp_bg, dp_ba = np.zeros((3, 3)), np.zeros((3, 3))
    for k in range(n):
        w, a, d = gyro[k] - bg, acc[k] - ba, dt[k]
        dr = so3_exp(w * d)
        jr = right_jacobian(w * d)
        A = np.eye(9)
        A[0:3, 0:3] = dr.T
        A[3:6, 0:3] = -R @ skew(a) * d
        A[6:9, 0:3] = -0.5 * R @ skew(a) * d * d
        A[6:9, 3:6] = np.eye(3) * d
        B = np.zeros((9, 6))
        B[0:3, 0:3] = jr * d
        B[3:6, 3:6] = R * d
        B[6:9, 3:6] = 0.5 * R * d * d
        Q = np.diag(np.concatenate([sg**2, sa**2])) / d
        cov = A @ cov @ A.T + B @ Q @ B.T
        cov[6:9, 6:9] += si**2 * d * np.eye(3)
        # bias Jacobians (uses the rotation before the sample)
        dp_ba = dp_ba + dv_ba * d - 0.5 * R * d * d
        dp_bg = dp_bg + dv_bg * d - 0.5 * R @ skew(a) @ dR_bg * d * d
        dv_ba = dv_ba - R * d
        dv_bg = dv_bg - R @ skew(a) @ dR_bg * d
        dR_bg = dr.T @ dR_bg - jr * d
        # values
        p = p + v * d + 0.5 * R @ a * d * d
        v = v + R @ a * d
        R = R @ dr
    jac = np.zeros((9, 6))
    jac[0:3, 0:3] = dR_bg
    jac[3:6, 0:3], jac[3:6, 3:6] = dv_bg, dv_ba
    jac[6:9, 0:3], jac[6:9, 3:6] = dp_bg, dp_ba
    return R, v, p, cov, jac


def dead_reckoning(gyro, acc, dt, gravity, R0=np.eye(3), v0=np.zeros(3), p0=np.zeros(3)):
    """Strapdown integration (zero-order hold): the states after every sample."""
    R, v, p = R0.copy(), v0.copy(), p0.copy()
    out = []
    for k in range(len(dt)):
        d = dt[k]
        a_nav = R @ acc[k] + gravity
        p = p + v * d + 0.5 * a_nav * d * d
        v = v + a_nav * d
        R = R @ so3_exp(gyro[k] * d)
        out.append((R.copy(), v.copy(), p.copy()))
    return out


def random_window(seed: int, n: int, rate: float = 0.8, accel: float = 2.0,
                  variable_dt: bool = True):
    """Seeded IMU samples (gyro, acc with gravity along +z on average, dt)."""
    rng = np.random.default_rng(seed)
    gyro = rng.normal(size=(n, 3)) * rate
    acc = rng.normal(size=(n, 3)) * accel + np.array([0.0, 0.0, 9.81])
    dt = rng.uniform(0.004, 0.006, size=n) if variable_dt else np.full(n, 0.005)
    return gyro, acc, dt
