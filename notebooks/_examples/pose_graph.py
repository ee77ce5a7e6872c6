"""Pose-graph optimisation with sparse factor graphs.

A pose graph has one SE(3) (or SE(2)) pose per vertex and one relative-pose measurement
per edge; the residual of an edge (i, j) with measurement Z is ``Log(Z⁻¹·Xi⁻¹·Xj)``
(translation first), weighted by its information matrix. ``jaxpose.graph`` stacks the
variables per type, evaluates the factors of each type with ``vmap``, builds the sparsity
pattern of ``JᵀJ`` once, and runs Levenberg–Marquardt with a sparse Cholesky, block-Jacobi
PCG or a dense solve — all in one jitted ``lax.while_loop``.

This tutorial optimises a generated noisy sphere (no data needed), plots it before and
after against the ground truth, makes it robust to false loop closures with a kernel, and
— when the benchmark graphs of ``../shared/data/g2o`` are present — solves real data sets
and compares the final costs with GTSAM's.

Run ``python notebooks/_examples/pose_graph.py`` (``JAXPOSE_NOTEBOOK_SMOKE=1`` for tiny
sizes).
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
import matplotlib.pyplot as plt
import numpy as np

import jaxpose as jp
from jaxpose.geometry import ape
from jaxpose.graph import (
    Factor,
    FactorGraph,
    between_residual,
    optimize_pose_graph,
    solve,
    summary,
)

jax.config.update("jax_enable_x64", True)
SMOKE = os.environ.get("JAXPOSE_NOTEBOOK_SMOKE") == "1"  # tiny sizes (CI runs every notebook)

# %% [markdown]
# ## A generated graph
#
# `jp.synthetic_pose_graph` draws poses on rings around a sphere (like the classic
# sphere2500 benchmark), odometry edges between consecutive poses and loop closures
# between neighbouring rings, with noisy measurements; the initial guess chains the noisy
# odometry, so it drifts. It returns the same `PoseGraph` container as `jp.read_g2o`.

# %%
n_poses = 60 if SMOKE else 900
graph, truth = jp.synthetic_pose_graph("SE3", n_poses=n_poses, noise=(0.02, 0.05), seed=0)
print(f"{graph.kind}: {len(graph.poses)} poses, {len(graph.edges)} edges "
      f"({len(graph.edges) - (n_poses - 1)} loop closures)")
print("poses", graph.poses.shape, "edges", graph.edges.shape,
      "measurements", graph.measurements.shape, "information", graph.information.shape)

# %% [markdown]
# ## Factors and the graph
#
# A `Factor` describes *m* factors of one type at once: a residual written for ONE factor
# (vmapped inside), the variable slots it touches (a type name and an index array per
# slot), per-factor data and information matrices. `between_residual` comes with its
# analytic Jacobian (`between_jacobian`, used automatically); other residuals are
# differentiated by autodiff unless you pass `jacobian=`. Fixing pose 0 removes the gauge
# freedom.

# %%
def build(graph, kernel=None):
    factor = Factor(
        between_residual,
        [("pose", graph.edges[:, 0]), ("pose", graph.edges[:, 1])],
        data=jp.SE3(graph.measurements),
        information=graph.information,
        kernel=kernel,
    )
    return FactorGraph([factor], {"pose": jp.SE3(graph.poses)}, fixed={"pose": [0]})


problem = build(graph)
t0 = time.perf_counter()
sol = jax.jit(solve)(problem)
jax.block_until_ready(sol)
print(f"solved in {time.perf_counter() - t0:.1f} s (compilation included)")
print(summary(sol))

# %% [markdown]
# ## Before and after
#
# Positions (x–y and x–z) of the initial guess, the optimised graph and the ground truth,
# and the cost per iteration. `jaxpose.geometry.ape` measures the absolute trajectory
# error after an SE(3) alignment (the gauge of the truth and of the estimate differ).

# %%
est = sol.variables["pose"]
for name, poses in (("initial", jp.SE3(graph.poses)), ("optimised", est)):
    err = ape(jp.SE3(truth), poses, align="se3")
    print(f"{name:9s} APE RMSE {float(err.stats.rmse):.4f}")

fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
for ax, (a, b) in zip(axes[:2], ((0, 1), (0, 2))):
    ax.plot(graph.poses[:, a], graph.poses[:, b], lw=0.6, label="initial (odometry)")
    ax.plot(est.data[:, a], est.data[:, b], lw=0.8, label="optimised")
    ax.plot(truth[:, a], truth[:, b], "k:", lw=0.8, label="ground truth")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"{'xyz'[a]}–{'xyz'[b]}")
axes[0].legend()
history = np.asarray(sol.history)
axes[2].semilogy(history[np.isfinite(history)], "o-")
axes[2].set_xlabel("iteration")
axes[2].set_ylabel("cost 0.5·Σ rᵀΩr")
plt.tight_layout()
plt.show()

# %% [markdown]
# ## False loop closures and robust kernels
#
# Add loop closures between random, unrelated poses (claiming they coincide). Plain least
# squares bends the whole graph to satisfy them; a Cauchy kernel on the edges down-weights
# them. The kernel acts on the squared whitened norm s = rᵀΩr of each edge, which is about
# 6 (the residual dimension) for a correct edge, hence the scale δ = 3 (δ² = 9).

# %%
rng = np.random.default_rng(1)
n_bad = 5 if SMOKE else 20
bad = rng.choice(n_poses, size=(n_bad, 2), replace=False)
identity = np.tile([0.0, 0, 0, 0, 0, 0, 1], (n_bad, 1))
corrupted = graph.__class__(
    kind=graph.kind,
    vertex_ids=graph.vertex_ids,
    poses=graph.poses,
    edges=np.concatenate([graph.edges, bad]),
    measurements=np.concatenate([graph.measurements, identity]),
    information=np.concatenate([graph.information, graph.information[:n_bad]]),
)
for name, kernel in (("no kernel", None), ("Cauchy(3)", jp.optim.Cauchy(3.0))):
    s = jax.jit(solve)(build(corrupted, kernel))
    err = ape(jp.SE3(truth), s.variables["pose"], align="se3")
    print(f"{name:10s} {s.status_name:10s} {int(s.iterations):3d} iterations, "
          f"APE RMSE {float(err.stats.rmse):.4f}")

# %% [markdown]
# ## Real benchmark graphs (when `../shared/data` is present)
#
# `jp.read_g2o` reads `VERTEX_SE3:QUAT`/`EDGE_SE3:QUAT` and `VERTEX_SE2`/`EDGE_SE2` files;
# `optimize_pose_graph` builds the factor graph above and solves it. GTSAM's
# Levenberg–Marquardt reaches the final costs in the table below on the same files
# (first pose fixed). On Colab this section is skipped unless you upload a g2o file and
# set `DATA` to its folder.

# %%
GTSAM_COST = {"tinyGrid3D.g2o": 9.313909, "smallGrid3D.g2o": 517.9253,
              "parking-garage.g2o": 0.6341924, "intel.g2o": 22.50212}


def find_data() -> Path | None:
    for base in (Path.cwd(), *Path.cwd().parents):
        if (base / "shared" / "data" / "g2o").is_dir():
            return base / "shared" / "data" / "g2o"
    return None


DATA = find_data()
names = ["smallGrid3D.g2o"] if SMOKE else ["smallGrid3D.g2o", "parking-garage.g2o", "intel.g2o"]
if DATA is None:
    print("no ../shared/data/g2o folder: skipping the real data sets")
else:
    for name in names:
        g = jp.read_g2o(DATA / name)
        t0 = time.perf_counter()
        poses, s = optimize_pose_graph(g)
        dt = time.perf_counter() - t0
        print(f"{name:20s} {g.kind} {len(g.poses):5d} poses  cost {float(s.initial_cost):.6g} → "
              f"{float(s.cost):.7g} (GTSAM {GTSAM_COST[name]:.7g}), {int(s.iterations)} "
              f"iterations, {s.status_name}, {dt:.1f} s")
        fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
        for ax, (label, p) in zip(axes, (("initial", g.poses), ("optimised", poses))):
            ax.plot(p[:, 0], p[:, 1], lw=0.5)
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_title(f"{name}: {label} (x–y)")
        plt.show()
