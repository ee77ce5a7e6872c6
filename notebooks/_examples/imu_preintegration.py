"""IMU preintegration, dead reckoning and IMU + GPS fusion.

`jaxpose.imu` preintegrates gyroscope and accelerometer samples between two keyframes
on the manifold (Forster et al., RSS 2015 / T-RO 2017): the relative motion ΔR, Δv, Δp,
its 9×9 covariance from the sensors' noise densities, and the Jacobians of the deltas
w.r.t. the gyroscope and accelerometer biases (for first-order bias correction). Every
function is a pure JAX function: it jits, vmaps over windows, runs long sequences with
an associative scan, and differentiates w.r.t. the measurements, the biases and the noise
parameters.

This tutorial preintegrates a window and checks it against closed forms, corrects for a
new bias, batches 1000 windows, dead-reckons GTSAM's IMU + GPS example stream (when
``../shared/data/imu`` is present) and fuses it with the GPS fixes in a sparse factor
graph, with simulated sensor errors: dead-reckoning drift versus the fused estimate. The
last section learns an IMU calibration through the differentiable preintegrator.
Conventions (frames, gravity sign, state ordering, bias layout): ``docs/imu.md``.

Run ``python notebooks/_examples/imu_preintegration.py`` (``JAXPOSE_NOTEBOOK_SMOKE=1`` for
tiny sizes).
"""

from __future__ import annotations

import os
import sys

if __package__ in (None, ""):
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

# %% [markdown]
# ## Set-up

# %%
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import jaxpose as jp
from jaxpose.imu import NavState, fuse_imu_gps, preintegrate, read_imu_gps

jax.config.update("jax_enable_x64", True)
SMOKE = os.environ.get("JAXPOSE_NOTEBOOK_SMOKE") == "1"  # tiny sizes (CI runs every notebook)

# %% [markdown]
# ## One window
#
# The accelerometer measures the *specific force* `Rᵀ(a − g)`: an IMU at rest, z up,
# reads `[0, 0, +9.81]`. The deltas are gravity-free and expressed in the body frame at
# the window's start; gravity (a navigation-frame vector, `[0, 0, −9.81]` for z up) only
# enters when a state is predicted:
# `R_j = R_i ΔR`, `v_j = v_i + gΔt + R_i Δv`, `p_j = p_i + v_iΔt + ½gΔt² + R_i Δp`.
#
# Here the body spins at a constant rate about its z axis while at rest otherwise, so
# `ΔR = Exp(ωT)` exactly, and the prediction stays at the origin.

# %%
n, dt = 200, 0.005
omega = np.array([0.0, 0.0, 0.5])
gyro = np.tile(omega, (n, 1))
acc = np.tile([0.0, 0.0, 9.81], (n, 1))
pre = preintegrate(gyro, acc, dt, gyro_noise=2e-4, acc_noise=4e-3)
print("ΔR =", np.round(np.asarray(pre.rot.matrix()), 6).tolist())
print("Exp(ωT) =", np.round(np.asarray(jp.so3(jnp.asarray(omega * n * dt)).exp().matrix()),
                            6).tolist())
print("Δv =", np.asarray(pre.vel), " Δp =", np.asarray(pre.pos), " Δt =", float(pre.dt))
print("σ of [δφ, δv, δp]:", np.sqrt(np.diag(np.asarray(pre.cov))).round(6))
end = pre.predict(NavState.identity(), [0.0, 0.0, -9.81])
print("predicted velocity", np.asarray(end.vel), "position", np.asarray(end.pos))

# %% [markdown]
# ## Bias correction
#
# `pre.jac` (9 × 6) holds ∂[φ, v, p]/∂[b_g, b_a] at the biases used for preintegration.
# When an optimiser moves the bias estimate by δb, the deltas are corrected to first
# order (`ΔR·Exp(J_R δb_g)`, `Δv + J_v δb`, `Δp + J_p δb`) instead of re-integrating; the
# error shrinks quadratically with δb.

# %%
rng = np.random.default_rng(0)
gyro = rng.normal(size=(n, 3)) * 0.5
acc = rng.normal(size=(n, 3)) + np.array([0.0, 0.0, 9.81])
pre = preintegrate(gyro, acc, dt, gyro_noise=2e-4, acc_noise=4e-3)
for eps in (1e-2, 1e-3, 1e-4):
    bg, ba = eps * np.array([1.0, -2.0, 0.5]), eps * np.array([3.0, 1.0, -2.0])
    rot, vel, pos = pre.corrected(bg, ba)
    again = preintegrate(gyro, acc, dt, gyro_bias=bg, acc_bias=ba)
    e = float(jnp.abs(pos - again.pos).max())
    print(f"|δb| ~ {eps:.0e}: first-order correction error {e:.2e} m")

# %% [markdown]
# ## Many windows, long sequences
#
# Leading axes are batch axes (or use `jax.vmap`). Rotations accumulate with an associative
# prefix product; each window's covariance and bias Jacobians come from a closed-form gain
# per sample, without a sequential recurrence. `bench/imu.py` compares the speed with
# PyPose's `IMUPreintegrator`.

# %%
windows = 100 if SMOKE else 1000
g = jnp.asarray(rng.normal(size=(windows, 200, 3)) * 0.5)
a = jnp.asarray(rng.normal(size=(windows, 200, 3)) + np.array([0.0, 0.0, 9.81]))
batched = jax.jit(lambda g, a: preintegrate(g, a, dt, gyro_noise=2e-4, acc_noise=4e-3))
jax.block_until_ready(batched(g, a))
t0 = time.perf_counter()
out = jax.block_until_ready(batched(g, a))
print(f"{windows} windows × 200 samples, values + covariance + bias Jacobians: "
      f"{(time.perf_counter() - t0) * 1e3:.1f} ms; cov {out.cov.shape}")

# %% [markdown]
# ## GTSAM's IMU + GPS stream: dead reckoning and fusion
#
# `imuAndGPSdata.csv` (GTSAM's `ImuFactorsExample`) holds 20 000 IMU samples at 200 Hz and
# 100 GPS fixes (position and ground-truth orientation), with zero gravity. The stream is
# noise-free: dead reckoning from rest reproduces the fixes. To see drift we add constant
# biases and white noise at the example's noise densities to the IMU, and 0.5-m noise to
# the fixes used as measurements (errors are measured against the clean fixes).
#
# `fuse_imu_gps` places a keyframe at the start and at every fix, preintegrates the IMU
# between keyframes, and solves a factor graph (IMU factors, GPS factors, bias random
# walk, priors on the first state) with sparse Levenberg–Marquardt.
#
# The attitude is only partly observable here: with zero gravity and a specific force
# along x only, a rotation about x changes no measurement, so the x component of the gyro
# bias cannot be estimated and the fused attitude error grows with it (pitch and yaw are
# corrected through the positions).

# %%
# the data sit next to the repository: ../shared/data from its root (notebooks/: ../../)
CANDIDATES = [Path(*[".."] * k, "shared", "data", "imu", "imuAndGPSdata.csv") for k in (2, 1, 3)]
DATA = next((p for p in CANDIDATES if p.is_file()), CANDIDATES[0])
HAVE_DATA = DATA.is_file()
if HAVE_DATA:
    d = read_imu_gps(DATA)
    fixes = 11 if SMOKE else len(d.gps_index)
    n_imu = int(d.gps_index[fixes - 1])
    truth = d.gps_position[:fixes]
    init = NavState(jp.SO3(jnp.asarray(d.init_rotation)), d.init_velocity, d.init_position)
    print(f"{n_imu} IMU samples, {fixes} fixes; initial row layout {d.initial_layout}")

    rng = np.random.default_rng(0)
    bias_g, bias_a = np.array([2e-4, -1e-4, 3e-4]), np.array([0.02, -0.01, 0.015])
    white = lambda sigma: rng.normal(size=(n_imu, 3)) * sigma / np.sqrt(0.005)  # noqa: E731
    gyro = d.gyro[:n_imu] + bias_g + white(2.05689024915e-4)
    acc = d.acc[:n_imu] + bias_a + white(3.924e-4)
    z = truth + rng.normal(size=truth.shape) * 0.5

    t0 = time.perf_counter()
    res = fuse_imu_gps(gyro, acc, 0.005, d.gps_index[:fixes], z, init, gps_sigma=0.5)
    print(f"fused in {time.perf_counter() - t0:.1f} s (incl. compile): "
          f"{res.solution.status_name}, {int(res.solution.iterations)} iterations")
    kf = np.searchsorted(res.keyframes, d.gps_index[:fixes])
    err = lambda p: np.linalg.norm(np.asarray(p) - truth, axis=1)  # noqa: E731
    drift, fused = err(res.dead_reckoning.pos[kf]), err(res.pose.data[kf, :3])
    rot = lambda q: np.degrees(np.linalg.norm(np.asarray(jp.SO3(q).log().data), axis=-1))  # noqa: E731
    print("| position error vs GPS truth [m] | final | RMS | max |")
    print("|---|---:|---:|---:|")
    for name, e in (("dead reckoning", drift), ("fused", fused)):
        print(f"| {name} | {e[-1]:.3f} | {np.sqrt(np.mean(e**2)):.3f} | {e.max():.3f} |")
    print(f"rotation error vs GPS orientations [deg]: dead reckoning max "
          f"{rot(res.dead_reckoning.rot.data[kf]).max():.3f}, fused max "
          f"{rot(res.pose.data[kf, 3:7]).max():.3f}")
    print("estimated accelerometer bias at the end", np.asarray(res.bias[-1, 3:]).round(4),
          "(true", bias_a, ")")
else:
    print(f"{DATA} not found: skipping the fusion example")

# %%
if HAVE_DATA:
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 3.8))
    t = d.gps_index[:fixes] * 0.005
    ax1.plot(t, drift, label="dead reckoning")
    ax1.plot(t, fused, label="IMU + GPS fused")
    ax1.set_xlabel("time [s]")
    ax1.set_ylabel("position error [m]")
    ax1.set_yscale("log")
    ax1.legend()
    dr_pos, fused_pos = np.asarray(res.dead_reckoning.pos[kf]), np.asarray(res.pose.data[kf])
    ax2.plot(truth[:, 0], truth[:, 2], "k.", ms=3, label="GPS (truth)")
    ax2.plot(dr_pos[:, 0], dr_pos[:, 2], label="dead reckoning")
    ax2.plot(fused_pos[:, 0], fused_pos[:, 2], label="fused")
    ax2.set_xlabel("north [m]")
    ax2.set_ylabel("down [m]")
    ax2.legend()
    fig.tight_layout()
    plt.show()
