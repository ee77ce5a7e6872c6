"""IMU, GPS and bias factors for the sparse least-squares path (:mod:`jaxpose.graph`).

Variables (names configurable): ``"pose"`` :class:`~jaxpose.lie.SE3` (n,) body-to-
navigation poses ``[p, q]``, ``"vel"`` (n, 3) navigation-frame velocities, ``"bias"``
(n, 6) IMU biases ``[b_g, b_a]``. Conventions: ``docs/imu.md``.

* :func:`imu_factor` — Forster et al.'s preintegrated IMU factor (their eq. 45) between
  keyframes i and j, residual ``[r_R, r_v, r_p]`` (9,) in the preintegration's chart::

      r_R = Log((ΔR̃·Exp(J_R^g δb_g))ᵀ R_iᵀ R_j)
      r_v = R_iᵀ(v_j − v_i − g Δt) − (Δṽ + J_v δb)
      r_p = R_iᵀ(p_j − p_i − v_i Δt − ½ g Δt²) − (Δp̃ + J_p δb)

  with ``δb = b_i − b̂`` (first-order bias correction) and information ``Σ⁻¹`` of the
  preintegration covariance (ordered ``[δφ, δv, δp]``, as the residual).
* :func:`gps_factor` — position fix: ``t(X) − z`` (GTSAM's ``GPSFactor``).
* :func:`bias_walk_factor` — bias random walk between keyframes: ``b_j − b_i`` with
  covariance ``diag(σ_bg², σ_ba²)·Δt``.

Residual functions are written for one factor (the graph vmaps them); Jacobians come from
forward-mode autodiff through the pose retraction ``X ⊕ δ = X·Exp(δ)``.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..graph._factor import Factor
from ..lie import SE3
from ..lie import _quaternion as quat
from ..lie._base import skew
from ._checks import as_float
from ._preintegration import Preintegrated

Array = jax.Array


class ImuFactorData(eqx.Module):
    """Per-factor data of :func:`imu_residual` (leading axis m in a :class:`Factor`).

    ``rot`` ΔR̃ quaternion (4,), ``vel``/``pos`` Δṽ, Δp̃ (3,), ``dt`` Δt (), ``jac`` (9, 6)
    bias Jacobians, ``bias_hat`` (6,) linearisation biases ``[b_g, b_a]``, ``gravity``
    (3,) in the navigation frame."""

    rot: Array
    vel: Array
    pos: Array
    dt: Array
    jac: Array
    bias_hat: Array
    gravity: Array


def imu_residual(
    pose_i: SE3, vel_i: Array, pose_j: SE3, vel_j: Array, bias_i: Array, data: ImuFactorData
) -> Array:
    """Residual ``[r_R, r_v, r_p]`` (9,) of one preintegrated IMU factor (module doc)."""
    qi, pi = pose_i.data[3:7], pose_i.data[0:3]
    qj, pj = pose_j.data[3:7], pose_j.data[0:3]
    d = data.jac @ (bias_i - data.bias_hat)
    drot = quat.multiply(data.rot, quat.exp(d[0:3]))
    dv, dp = data.vel + d[3:6], data.pos + d[6:9]
    t, g = data.dt, data.gravity
    qi_inv = quat.conjugate(qi)
    r_rot = quat.log(quat.multiply(quat.conjugate(drot), quat.multiply(qi_inv, qj)))
    r_vel = quat.rotate(qi_inv, vel_j - vel_i - g * t) - dv
    r_pos = quat.rotate(qi_inv, pj - pi - vel_i * t - 0.5 * g * t * t) - dp
    return jnp.concatenate([r_rot, r_vel, r_pos])


def imu_jacobian(
    pose_i: SE3, vel_i: Array, pose_j: SE3, vel_j: Array, bias_i: Array, data: ImuFactorData
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Residual and analytic Jacobians of :func:`imu_residual` (Forster et al.'s
    supplementary material) w.r.t. the right perturbations of pose_i (9, 6) ``[ρ, φ]``,
    vel_i (9, 3), pose_j (9, 6), vel_j (9, 3) and bias_i (9, 6) ``[b_g, b_a]``::

        ∂r_R/∂φ_i = −Jr⁻¹(r_R)·R_jᵀR_i,   ∂r_R/∂φ_j = Jr⁻¹(r_R),
        ∂r_R/∂b_g = −Jr⁻¹(r_R)·Exp(r_R)ᵀ·Jr(J_R^g δb_g)·J_R^g,
        ∂r_v/∂φ_i = [R_iᵀ(v_j − v_i − gΔt)]×,  ∂r_v/∂v_i = −R_iᵀ,  ∂r_v/∂v_j = R_iᵀ,
        ∂r_p/∂ρ_i = −I,  ∂r_p/∂φ_i = [R_iᵀ(p_j − p_i − v_iΔt − ½gΔt²)]×,
        ∂r_p/∂ρ_j = R_iᵀR_j,  ∂r_p/∂v_i = −R_iᵀΔt,  ∂r_{v,p}/∂b = −J_{v,p}.
    """
    qi, pi = pose_i.data[3:7], pose_i.data[0:3]
    qj, pj = pose_j.data[3:7], pose_j.data[0:3]
    dtype = pi.dtype
    d = data.jac @ (bias_i - data.bias_hat)
    dphi = d[0:3]
    drot = quat.multiply(data.rot, quat.exp(dphi))
    t, g = data.dt, data.gravity
    qi_inv = quat.conjugate(qi)
    r_rot = quat.log(quat.multiply(quat.conjugate(drot), quat.multiply(qi_inv, qj)))
    rel_v = quat.rotate(qi_inv, vel_j - vel_i - g * t)
    rel_p = quat.rotate(qi_inv, pj - pi - vel_i * t - 0.5 * g * t * t)
    r = jnp.concatenate([r_rot, rel_v - data.vel - d[3:6], rel_p - data.pos - d[6:9]])
    ri_t = quat.to_matrix(qi_inv)
    rij = quat.to_matrix(quat.multiply(qi_inv, qj))  # R_iᵀR_j
    jr_inv = quat.jl_inv(-r_rot)
    eye, z3 = jnp.eye(3, dtype=dtype), jnp.zeros((3, 3), dtype)
    j_pose_i = jnp.block([
        [z3, -jr_inv @ rij.T],
        [z3, skew(rel_v)],
        [-eye, skew(rel_p)],
    ])
    j_pose_j = jnp.block([[z3, jr_inv], [z3, z3], [rij, z3]])
    j_vel_i = jnp.concatenate([z3, -ri_t, -ri_t * t])
    j_vel_j = jnp.concatenate([z3, ri_t, z3])
    j_rot_bg = -jr_inv @ quat.to_matrix(quat.exp(-r_rot)) @ quat.jl(-dphi) @ data.jac[0:3, 0:3]
    j_bias = jnp.concatenate([
        jnp.concatenate([j_rot_bg, z3], -1),
        -data.jac[3:9],
    ])
    return r, j_pose_i, j_vel_i, j_pose_j, j_vel_j, j_bias


def _indices(x: Any, m: int, name: str) -> np.ndarray:
    idx = np.asarray(x)
    if idx.ndim == 0:
        idx = np.full(m, int(idx))
    if idx.shape != (m,) or not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"{name}: expected {m} integer indices, got shape {idx.shape} "
                         f"dtype {idx.dtype}")
    return idx


def imu_factor(
    pre: Preintegrated,
    i: Any,
    j: Any,
    gravity: Any,
    *,
    pose: str = "pose",
    vel: str = "vel",
    bias: str = "bias",
    kernel: Any = None,
    name: str = "imu",
    analytic_jacobian: bool = True,
) -> Factor:
    """m preintegrated IMU factors between keyframes ``i[k]`` and ``j[k]``.

    Args:
        pre: :class:`Preintegrated` with batch shape (m,), covariance and bias Jacobians
            (``preintegrate(..., gyro_noise=..., acc_noise=...)``).
        i, j: (m,) keyframe indices (into the pose, velocity and bias variables).
        gravity: (3,) navigation-frame gravity vector (e.g. ``[0, 0, -9.81]``, z up).
        pose, vel, bias: variable-type names in the :class:`~jaxpose.graph.FactorGraph`.
        analytic_jacobian: use :func:`imu_jacobian` (default; much cheaper to compile)
            instead of forward-mode autodiff of :func:`imu_residual`.
    Must be called outside ``jit`` (the information matrices are factorised on the host).
    """
    if not isinstance(pre, Preintegrated):
        raise TypeError(f"imu_factor(pre): expected Preintegrated, got {type(pre).__name__}")
    if pre.cov is None or pre.jac is None:
        raise ValueError("imu_factor(pre): needs the covariance and the bias Jacobians "
                         "(preintegrate(..., gyro_noise=..., acc_noise=..., "
                         "bias_jacobians=True))")
    if pre.vel.ndim != 2:
        raise ValueError(f"imu_factor(pre): expected a batch of shape (m,), got "
                         f"{pre.vel.shape[:-1]}")
    m = pre.vel.shape[0]
    ii, jj = _indices(i, m, "imu_factor(i)"), _indices(j, m, "imu_factor(j)")
    g = as_float(gravity, "imu_factor(gravity)")
    if g.shape != (3,):
        raise ValueError(f"imu_factor(gravity): expected a 3-vector, got shape {g.shape}")
    dtype = pre.vel.dtype
    data = ImuFactorData(
        rot=pre.rot.data, vel=pre.vel, pos=pre.pos, dt=pre.dt, jac=pre.jac,
        bias_hat=jnp.concatenate([pre.gyro_bias, pre.acc_bias], -1),
        gravity=jnp.broadcast_to(g.astype(dtype), (m, 3)),
    )
    cov = np.asarray(pre.cov, dtype=np.float64)
    if not np.all(np.isfinite(cov)):
        raise ValueError("imu_factor(pre): the covariance contains NaN or inf")
    w = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    bad = np.flatnonzero(~(w[:, 0] > 9 * np.finfo(pre.cov.dtype).eps * w[:, -1]))
    if bad.size:
        raise ValueError(f"imu_factor(pre): the covariance of window {int(bad[0])} is "
                         f"singular (a zero noise density gives infinite information); "
                         f"give positive gyro_noise and acc_noise")
    info = np.linalg.inv(cov)
    info = 0.5 * (info + np.swapaxes(info, -1, -2))
    return Factor(imu_residual, [(pose, ii), (vel, ii), (pose, jj), (vel, jj), (bias, ii)],
                  data=data, information=info, kernel=kernel, name=name,
                  jacobian=imu_jacobian if analytic_jacobian else None)


def gps_residual(pose: SE3, z: Array) -> Array:
    """Position residual ``t(X) − z`` (3,) (GTSAM's ``GPSFactor``: the body origin)."""
    return pose.data[0:3] - z


def gps_jacobian(pose: SE3, z: Array) -> tuple[Array, Array]:
    """Residual and Jacobian ``[R, 0]`` (3, 6) of :func:`gps_residual`."""
    rot = quat.to_matrix(pose.data[3:7])
    return pose.data[0:3] - z, jnp.concatenate([rot, jnp.zeros_like(rot)], -1)


def _information(sigma: Any, information: Any, dim: int, fn: str) -> Any:
    if (sigma is None) == (information is None):
        raise ValueError(f"{fn}: give exactly one of sigma and information")
    if information is not None:
        shape = np.shape(information)
        if shape[-2:] != (dim, dim) or len(shape) not in (2, 3):
            raise ValueError(f"{fn}(information): expected shape ({dim}, {dim}) or "
                             f"(m, {dim}, {dim}), got {shape}")
        return information
    s = np.asarray(sigma, dtype=np.float64)
    if s.shape not in ((), (dim,)) or not np.all(s > 0):
        raise ValueError(f"{fn}(sigma): expected a positive scalar or ({dim},) σ, got {s!r}")
    return np.diag(np.broadcast_to(1.0 / (s * s), (dim,)))


def gps_factor(
    positions: Any,
    index: Any,
    *,
    sigma: Any = None,
    information: Any = None,
    pose: str = "pose",
    kernel: Any = None,
    name: str = "gps",
) -> Factor:
    """m position fixes ``positions`` (m, 3) of the poses ``index`` (m,); noise ``sigma``
    (scalar or (3,), metres) or ``information`` ((3, 3) or (m, 3, 3))."""
    z = as_float(positions, "gps_factor(positions)")
    if z.ndim != 2 or z.shape[-1] != 3:
        raise ValueError(f"gps_factor(positions): expected shape (m, 3), got {z.shape}")
    idx = _indices(index, z.shape[0], "gps_factor(index)")
    info = _information(sigma, information, 3, "gps_factor")
    return Factor(gps_residual, [(pose, idx)], data=z, information=info, kernel=kernel,
                  name=name, jacobian=gps_jacobian)


def pose_prior_residual(pose: SE3, z: SE3) -> Array:
    """Pose prior ``[t − t_z, Log(R_zᵀR)]`` (6,), ordered like the SE3 tangent ``[ρ, φ]``
    (position error in the navigation frame; GTSAM's ``PriorFactor<Pose3>`` uses
    ``Log(Z⁻¹X)``, which agrees to first order at the prior mean)."""
    rot = quat.log(quat.multiply(quat.conjugate(z.data[3:7]), pose.data[3:7]))
    return jnp.concatenate([pose.data[0:3] - z.data[0:3], rot])


def pose_prior_jacobian(pose: SE3, z: SE3) -> tuple[Array, Array]:
    """Residual and Jacobian ``blockdiag(R, Jr⁻¹(r_R))`` (6, 6) of
    :func:`pose_prior_residual`."""
    r = pose_prior_residual(pose, z)
    rot = quat.to_matrix(pose.data[3:7])
    z3 = jnp.zeros_like(rot)
    return r, jnp.block([[rot, z3], [z3, quat.jl_inv(-r[3:6])]])


def pose_prior_factor(
    poses: SE3, index: Any, *, rot_sigma: Any, pos_sigma: Any, pose: str = "pose",
    name: str = "pose_prior",
) -> Factor:
    """Priors on the poses ``index`` (m,) with means ``poses`` (SE3 (m,)) and noise σ of
    the rotation [rad] and position [m] (scalars or (3,))."""
    if not isinstance(poses, SE3) or len(poses.shape) != 1:
        raise TypeError("pose_prior_factor(poses): expected SE3 with batch shape (m,)")
    idx = _indices(index, poses.shape[0], "pose_prior_factor(index)")
    s = np.concatenate([np.broadcast_to(np.asarray(pos_sigma, np.float64), (3,)),
                        np.broadcast_to(np.asarray(rot_sigma, np.float64), (3,))])
    if not np.all(s > 0):
        raise ValueError("pose_prior_factor(rot_sigma, pos_sigma): expected positive σ")
    return Factor(pose_prior_residual, [(pose, idx)], data=poses,
                  information=np.diag(1.0 / (s * s)), name=name,
                  jacobian=pose_prior_jacobian)


def bias_walk_residual(b_i: Array, b_j: Array, data: Any) -> Array:
    """Bias change ``b_j − b_i`` (6,)."""
    del data
    return b_j - b_i


def bias_walk_factor(
    i: Any,
    j: Any,
    dt: Any,
    gyro_walk: Any,
    acc_walk: Any,
    *,
    bias: str = "bias",
    name: str = "bias_walk",
) -> Factor:
    """Random-walk factors between biases ``i`` and ``j`` (m,) separated by ``dt`` (m,)
    seconds (a scalar: the same interval for every factor): covariance
    ``diag(σ_bg²·1₃, σ_ba²·1₃)·dt`` with walk densities ``gyro_walk`` [rad/s²/√Hz] and
    ``acc_walk`` [m/s³/√Hz] (scalars or (3,))."""
    d = np.asarray(dt, dtype=np.float64)
    if d.ndim > 1:
        raise ValueError(f"bias_walk_factor(dt): expected shape (m,), got {d.shape}")
    d = np.full(np.size(i), float(d)) if d.ndim == 0 else d
    m = d.shape[0]
    ii, jj = _indices(i, m, "bias_walk_factor(i)"), _indices(j, m, "bias_walk_factor(j)")
    if not np.all(d > 0):
        raise ValueError("bias_walk_factor(dt): every interval must be positive")
    walks = {}
    for name, value in (("gyro_walk", gyro_walk), ("acc_walk", acc_walk)):
        walks[name] = np.asarray(value, dtype=np.float64)
        if walks[name].shape not in ((), (3,)):
            raise ValueError(f"bias_walk_factor({name}): expected a scalar or (3,) σ, got "
                             f"shape {walks[name].shape}")
    sg = np.broadcast_to(walks["gyro_walk"], (3,))
    sa = np.broadcast_to(walks["acc_walk"], (3,))
    if not (np.all(sg > 0) and np.all(sa > 0)):
        raise ValueError("bias_walk_factor(gyro_walk, acc_walk): expected positive σ")
    var = np.concatenate([sg * sg, sa * sa])[None, :] * d[:, None]
    info = np.zeros((m, 6, 6))
    info[:, np.arange(6), np.arange(6)] = 1.0 / var
    return Factor(bias_walk_residual, [(bias, ii), (bias, jj)], information=info, name=name)
