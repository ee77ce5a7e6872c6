"""Fixed-lag smoothing: IMU + GPS online, and a 2D pose graph replayed pose by pose.

`jaxpose.smoothing.FixedLagSmoother` keeps the last K states of a stream in fixed-shape
arrays, adds each step's factors, solves the window by Gauss–Newton and marginalises the
oldest state into a Gaussian prior (a Schur complement, with first-estimate Jacobians as
GTSAM's `BatchFixedLagSmoother`). Its update is one jitted function of fixed shapes, so
a whole stream runs inside `lax.scan` and independent streams batch with `vmap`.

This tutorial runs it on GTSAM's IMU + GPS example stream (preintegrated IMU factors,
bias random walk, GPS fixes with simulated noise), plots the newest estimate with its
±3σ band against the fixes, compares the smoother's final trajectory with the full batch
solution, runs the same stream with incremental (iSAM2-style) updates, replays the Intel
pose graph with loop closures inside the window, and runs
several streams at once. Conventions: ``docs/smoothing.md``.

Run ``python notebooks/_examples/fixed_lag_smoother.py`` (``JAXPOSE_NOTEBOOK_SMOKE=1`` for
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

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

from jaxpose.imu import NavState, fuse_imu_gps, read_imu_gps
from jaxpose.lie import SO3
from jaxpose.smoothing import examples as ex

jax.config.update("jax_enable_x64", True)
SMOKE = os.environ.get("JAXPOSE_NOTEBOOK_SMOKE") == "1"  # tiny sizes (CI runs every notebook)
DATA = next((p for p in (Path("../shared/data"), Path("../../shared/data")) if p.exists()), None)

# %% [markdown]
# ## IMU + GPS
#
# One state per keyframe, `{"bias": [b_g, b_a], "pose": SE3, "vel": (3,)}`; a keyframe at
# the start and at every GPS fix (one per second). Between keyframes: the preintegrated
# IMU factor and the bias random walk (the *motion* residual); on each keyframe the GPS
# fix, and on the first one priors on pose, velocity and bias (the *unary* residual).
# `imu_gps_steps` builds exactly the factors of the batch `fuse_imu_gps`. The fixes of
# the published stream equal dead reckoning, so we add 0.5 m of noise to them. When the
# data set is absent a short synthetic stream (a circle) stands in.

# %%
FIXES = 12 if SMOKE else 100
WINDOW = 4 if SMOKE else 10
SIGMA = 0.5
rng = np.random.default_rng(0)

if DATA is not None and (DATA / "imu" / "imuAndGPSdata.csv").exists():
    d = read_imu_gps(DATA / "imu" / "imuAndGPSdata.csv")
    gyro, acc, gps_index = d.gyro, d.acc, d.gps_index[1:FIXES]
    truth = d.gps_position[1:FIXES]
    init = NavState(SO3(jnp.asarray(d.init_rotation)), d.init_velocity, d.init_position)
else:  # a circle: constant yaw rate and centripetal acceleration, zero gravity
    n = 200 * FIXES
    gyro = np.tile([0.0, 0.0, 0.2], (n, 1))
    acc = np.tile([0.0, 0.2, 0.0], (n, 1))
    gps_index = np.arange(200, n + 1, 200)[: FIXES - 1]
    t = gps_index * 0.005
    truth = np.stack([np.sin(0.2 * t) / 0.2 * 1.0, (1 - np.cos(0.2 * t)) / 0.2, 0 * t], -1)
    init = NavState(SO3.identity(), np.array([1.0, 0.0, 0.0]), np.zeros(3))
n = int(gps_index[-1])
gps = truth + rng.normal(size=truth.shape) * SIGMA
steps = ex.imu_gps_steps(gyro[:n], acc[:n], 0.005, gps_index, gps, init, gps_sigma=SIGMA)
smoother = ex.imu_gps_smoother(steps, WINDOW)

t0 = time.perf_counter()
res = ex.run(smoother, steps, covariance=True)
jax.block_until_ready(res.latest)
print(
    f"{len(gps_index) + 1} updates (window {WINDOW}) incl. compilation: "
    f"{time.perf_counter() - t0:.1f} s; Gauss-Newton iterations per update: "
    f"{np.asarray(res.iterations).tolist()[:12]}..."
)

# %% [markdown]
# ## Estimate and ±3σ band against GPS
#
# At every step, the newest state's position and its marginal standard deviation (the
# inverse of the window's information; the position block of the SE3 tangent `[ρ, φ]`
# is in the body frame, rotated here to the navigation frame). Index 0 of the stream is
# the start (no fix).

# %%
pos = np.asarray(res.latest["pose"].data[:, 0:3])
rot = np.asarray(res.latest["pose"].rotation().matrix())
# tangent layout of one state: bias (6), pose [ρ (3), φ (3)], vel (3)
cov_body = np.asarray(res.latest_cov)[:, 6:9, 6:9]
cov_nav = rot @ cov_body @ np.swapaxes(rot, 1, 2)
sigma = np.sqrt(np.diagonal(cov_nav, axis1=1, axis2=2))
time_s = np.concatenate([[0.0], gps_index * 0.005])
fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
for i, ax in enumerate(axes):
    ax.fill_between(
        time_s, pos[:, i] - 3 * sigma[:, i], pos[:, i] + 3 * sigma[:, i], alpha=0.3, label="±3σ"
    )
    ax.plot(time_s, pos[:, i], label="smoother (newest)")
    ax.plot(time_s[1:], gps[:, i], ".", label="GPS")
    ax.set_ylabel("xyz"[i] + " [m]")
axes[0].legend(loc="best")
axes[-1].set_xlabel("time [s]")
fig.tight_layout()
plt.show()
err = pos[1:] - truth
print(
    f"newest-state error: RMS {np.sqrt(np.mean(err**2)):.3f} m (GPS noise σ {SIGMA} m); "
    f"inside 3σ: {np.mean(np.abs(err) <= 3 * sigma[1:]):.0%} of the coordinates"
)

# %% [markdown]
# ## Against the full batch solution
#
# The smoother's final trajectory keeps, for every state, its last estimate before it was
# marginalised. The batch solution solves all keyframes at once with the same factors.

# %%
batch = fuse_imu_gps(gyro[:n], acc[:n], 0.005, gps_index, gps, init, gps_sigma=SIGMA)
traj = np.asarray(res.trajectory["pose"].data[:, 0:3])
diff = traj - np.asarray(batch.pose.data[:, 0:3])
print(
    f"final trajectory vs batch: RMS {np.sqrt(np.mean(diff**2)):.2e} m, "
    f"max {np.abs(diff).max():.2e} m (newest state: {np.abs(diff[-1]).max():.2e} m)"
)

# %% [markdown]
# ## Incremental updates
#
# With `relinearize_threshold` the smoother works as iSAM2 does: it keeps the window's
# elimination, takes the cached message out of the oldest state as the new prior, solves
# a new state at the cost of its own factors, and re-linearises only the states whose
# step exceeds the threshold. One step per update instead of Gauss–Newton to
# convergence: the trajectory stays within millimetres of the Gauss–Newton smoother's.

# %%
inc = ex.run(ex.imu_gps_smoother(steps, WINDOW, relinearize_threshold=0.1), steps)
traj_inc = np.asarray(inc.trajectory["pose"].data[:, 0:3])
print(
    f"re-linearised in {int(np.sum(inc.iterations))} of {len(inc.iterations)} updates; "
    f"final trajectory vs Gauss-Newton smoother: max {np.abs(traj_inc - traj).max():.2e} m, "
    f"vs batch: RMS {np.sqrt(np.mean((traj_inc - np.asarray(batch.pose.data[:, 0:3])) ** 2)):.2e} m"
)

# %% [markdown]
# ## A 2D pose graph, pose by pose
#
# `pose_graph_steps` replays a g2o pose graph: step k adds pose k, its odometry edge and
# its loop closures. Loop closures to poses that already left the window are dropped
# (GTSAM's fixed-lag smoothers drop the factors of marginalised variables too), those
# inside the window are used.

# %%
g2o = DATA / "g2o" / "intel.g2o" if DATA is not None else None
if g2o is not None and g2o.exists():
    from jaxpose.graph import optimize_pose_graph
    from jaxpose.io import read_g2o

    graph = read_g2o(g2o)
    poses = 60 if SMOKE else 400
    pg_steps = ex.pose_graph_steps(graph, num_poses=poses)
    pg = ex.run(ex.pose_graph_smoother(pg_steps, 6 if SMOKE else 30), pg_steps)
    keep = graph.edges.max(1) < poses
    sub = type(graph)(
        kind="SE2",
        vertex_ids=graph.vertex_ids[:poses],
        poses=graph.poses[:poses],
        edges=graph.edges[keep],
        measurements=graph.measurements[keep],
        information=graph.information[keep],
    )
    ref, _ = optimize_pose_graph(sub)
    xy = np.asarray(pg.trajectory["pose"].data[:, :2])
    plt.figure(figsize=(6, 6))
    plt.plot(graph.poses[:poses, 0], graph.poses[:poses, 1], ":", label="initial (odometry)")
    plt.plot(ref[:, 0], ref[:, 1], label="batch")
    plt.plot(xy[:, 0], xy[:, 1], "--", label="fixed-lag smoother")
    plt.axis("equal")
    plt.legend()
    plt.show()
    print(
        f"{poses} poses: smoother vs batch, RMS position difference "
        f"{np.sqrt(np.mean(np.sum((xy - ref[:, :2]) ** 2, 1))):.2e} m"
    )

# %% [markdown]
# ## Many streams at once
#
# The smoother is a pytree of arrays: `vmap` runs independent streams (here the IMU
# stream with different GPS noise draws) in one compiled program.

# %%
B = 2 if SMOKE else 8
noisy = truth[None] + rng.normal(size=(B, *truth.shape)) * SIGMA
datas = [
    ex.imu_gps_steps(gyro[:n], acc[:n], 0.005, gps_index, z, init, gps_sigma=SIGMA) for z in noisy
]
batched = jax.tree.map(lambda *a: jnp.stack(a), *[s.data for s in datas])
sms = eqx.filter_vmap(lambda _: ex.imu_gps_smoother(steps, WINDOW), axis_size=B)(jnp.arange(B))


@eqx.filter_jit
def run_many(sms, data):
    return jax.vmap(lambda s, dd: ex.run_scan(s, steps._replace(data=dd)))(sms, data)


final = run_many(sms, batched)
newest = jax.vmap(lambda s: s.latest())(final)
print(f"newest positions of {B} streams:\n", np.asarray(newest["pose"].data[:, :3]))
