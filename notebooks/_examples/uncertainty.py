"""Uncertainty of a solution: marginal covariances of factor graphs and least squares.

A least-squares solution is a point estimate; its Gauss–Newton (Laplace) approximation
also gives its uncertainty: δ ~ N(0, H⁻¹) in the tangent chart at the solution
(X = X*·Exp(δ)), H = JᵀJ the whitened Gauss–Newton matrix. ``jaxpose.graph.marginals``
returns the blocks of H⁻¹ that people look at — each pose's covariance and joint blocks of
chosen pairs — without forming H⁻¹ (selected inversion of the sparse Cholesky factor);
``jaxpose.optim.covariance`` returns the whole (dense) covariance of a ``least_squares``
solution and is differentiable.

This tutorial draws 2σ position ellipses on a 2D and a 3D pose graph, reads the joint
marginal of two poses (how well their *relative* pose is known), checks the covariance of
a curve fit against Monte-Carlo refits, and — when ``../shared/data/g2o`` is present —
computes every pose marginal of intel.g2o.

Run ``python notebooks/_examples/uncertainty.py`` (``JAXPOSE_NOTEBOOK_SMOKE=1`` for tiny
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
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import EllipseCollection

import jaxpose as jp
from jaxpose.graph import default_stopping, marginals, pose_graph_problem, solve
from jaxpose.lie import SE2
from jaxpose.optim import covariance, least_squares
from jaxpose.plot import ellipse_axes, position_covariances

jax.config.update("jax_enable_x64", True)
SMOKE = os.environ.get("JAXPOSE_NOTEBOOK_SMOKE") == "1"  # tiny sizes (CI runs every notebook)


def draw(ax, xy, cov2, every=1, color="tab:red"):
    """The trajectory and 2σ ellipses of (n, 2, 2) position covariances."""
    ax.plot(xy[:, 0], xy[:, 1], lw=0.7)
    w, h, a = ellipse_axes(cov2[::every])
    ax.add_collection(EllipseCollection(w, h, a, units="xy", offsets=xy[::every],
                                        offset_transform=ax.transData, facecolors="none",
                                        edgecolors=color, linewidths=0.7))
    ax.set_aspect("equal", adjustable="datalim")


# %% [markdown]
# ## A 2D pose graph
#
# A noisy SE(2) graph driving laps around a circle, its first pose held fixed (the
# gauge). After the solve, `marginals(problem, solution, "pose")` gives the (n, 3, 3)
# covariances in the se2 chart `[ρx, ρy, θ]` at each pose (right perturbation: ρ is in
# the pose's own frame). `jaxpose.plot.position_covariances` rotates the position block
# into the world frame, R Σ_ρρ Rᵀ, for plotting.

# %%
n_poses = 60 if SMOKE else 600
graph, truth = jp.synthetic_pose_graph("SE2", n_poses=n_poses, noise=(0.02, 0.02), seed=1)
problem = pose_graph_problem(graph)
sol = jax.jit(solve)(problem)
print(sol.status_name, f"cost {float(sol.cost):.4g}")

t0 = time.perf_counter()
m = jax.jit(lambda p, s: marginals(p, s, "pose", pairs=np.array([[0, n_poses - 1],
                                                                   [n_poses // 2,
                                                                    n_poses - 1]])))(
    problem, sol)
cov = np.asarray(m.covariances["pose"])
print(f"{cov.shape[0]} marginals in {time.perf_counter() - t0:.2f} s (with compilation)")
print("first pose (fixed):", np.abs(cov[0]).max(), "  last pose σ_x, σ_y, σ_θ:",
      np.sqrt(np.diag(cov[-1])))

poses = np.asarray(sol.variables["pose"].data)
fig, ax = plt.subplots(figsize=(6, 6))
draw(ax, poses[:, :2], position_covariances("SE2", poses, cov), every=max(1, n_poses // 150))
ax.set_title("SE(2) graph: 2σ position ellipses (grow away from the fixed first pose)")
plt.show()

# %% [markdown]
# ## Joint marginals: relative uncertainty
#
# The joint block `[[Σ_aa, Σ_ab], [Σ_ba, Σ_bb]]` of two poses says how well their
# *relative* pose is known: to first order the relative pose Xa⁻¹Xb moves by
# δ_rel = δb − Adj(Xb⁻¹Xa)·δa, so Σ_rel = A Σ_joint Aᵀ with A = [−Adj(Xb⁻¹Xa), I]. Two
# poses joined by loop closures can be much better known relative to each other than
# either is absolutely.

# %%
for (a, b), joint in zip([(0, n_poses - 1), (n_poses // 2, n_poses - 1)], m.joint):
    xa, xb = SE2(jnp.asarray(poses[a])), SE2(jnp.asarray(poses[b]))
    adj = np.asarray(xb.inv().compose(xa).adj_matrix())
    A = np.concatenate([-adj, np.eye(3)], 1)
    rel = A @ np.asarray(joint) @ A.T
    print(f"poses {a:3d},{b:3d}: absolute σ of pose {b}: {np.sqrt(np.diag(joint)[3:])}, "
          f"relative σ: {np.sqrt(np.diag(rel))}")

# %% [markdown]
# ## A 3D pose graph, projected to x–y
#
# For SE(3) the covariance is 6×6 in the se3 chart `[ρ, φ]` (translation first; GTSAM's
# Pose3 orders it `[ω, v]`, same right perturbation: `jaxpose.graph.se3_to_gtsam` swaps
# the blocks). The ellipses below are the x–y projections of the 3D position marginals.
# `jaxpose pgo FILE --plot out.png` draws the same ellipses for any g2o file.

# %%
n3 = 64 if SMOKE else 900
graph3, _ = jp.synthetic_pose_graph("SE3", n_poses=n3, noise=(0.02, 0.02), seed=2)
problem3 = pose_graph_problem(graph3)
sol3 = jax.jit(solve)(problem3)
cov3 = np.asarray(jax.jit(lambda p, s: marginals(p, s, "pose").covariances["pose"])(
    problem3, sol3))
poses3 = np.asarray(sol3.variables["pose"].data)
pos3 = position_covariances("SE3", poses3, cov3)
fig, ax = plt.subplots(figsize=(6, 6))
draw(ax, poses3[:, :2], pos3[:, :2, :2], every=max(1, n3 // 200))
ax.set_title("SE(3) sphere graph: 2σ ellipses of the x–y position marginals")
plt.show()

# %% [markdown]
# ## Methods
#
# `method="dense"` inverts H densely (small graphs; jit, vmap and grad), `"sparse"` runs
# CHOLMOD's supernodal factorisation and the selected inversion on the host (the default
# above 600 tangent dimensions), `"pcg"` solves one preconditioned CG system per requested
# column on any device. They agree:

# %%
sub = {"pose": np.arange(0, n_poses, max(1, n_poses // 10))}
res = jax.jit(lambda p, s: [marginals(p, s, sub, method=k).covariances["pose"]
                            for k in ("dense", "sparse", "pcg")])(problem, sol)
print("max |sparse − dense| / max|dense|:",
      float(jnp.abs(res[1] - res[0]).max() / jnp.abs(res[0]).max()))
print("max |pcg − dense| / max|dense|:   ",
      float(jnp.abs(res[2] - res[0]).max() / jnp.abs(res[0]).max()))

# %% [markdown]
# ## Covariance of a least-squares fit
#
# `jaxpose.optim.covariance(residual_fn, params, args)` is Ceres' `Covariance` for
# `least_squares`: (JᵀJ)⁻¹ at the solution, over any pytree of groups and arrays
# (flat matrix in `ravel_pytree` tangent order, or `flat=False` for nested blocks). With
# residuals whitened by the true noise, it matches the spread of refits over noise draws:

# %%
sigma, n_obs = 0.1, 40
t = jnp.linspace(0.0, 2.0, n_obs)
true = {"a": jnp.asarray(1.5), "b": jnp.asarray(-0.8)}


def residual(p, y):
    return (p["a"] * jnp.exp(p["b"] * t) - y) / sigma


def fit(key):
    y = true["a"] * jnp.exp(true["b"] * t) + sigma * jax.random.normal(key, (n_obs,))
    return least_squares(residual, {"a": jnp.asarray(1.0), "b": jnp.asarray(-0.5)}, y).params, y


draws = 100 if SMOKE else 2000
fits, ys = jax.jit(jax.vmap(fit))(jax.random.split(jax.random.key(0), draws))
p0 = jax.tree.map(lambda v: v[0], fits)
predicted = covariance(residual, p0, ys[0])
empirical = np.cov(np.stack([np.asarray(fits["a"]), np.asarray(fits["b"])]))
print("predicted covariance (a, b):\n", np.asarray(predicted))
print(f"empirical over {draws} refits:\n", empirical)

# it is differentiable: the sensitivity of σ_a to the noise level of the data
grad = jax.grad(lambda s: jnp.sqrt(covariance(
    lambda p, y: residual(p, y) * sigma / s, p0, ys[0])[0, 0]))(sigma)
print("d σ_a / d σ_noise =", float(grad), "(σ_a is linear in σ_noise: σ_a/σ_noise =",
      float(jnp.sqrt(predicted[0, 0]) / sigma), ")")

# %% [markdown]
# ## A benchmark graph (when ../shared/data is present)
#
# All 1728 pose marginals of intel.g2o (CHOLMOD + selected inversion); `bench/marginals.py`
# times this and sphere2500 against GTSAM's `Marginals`.

# %%
path = Path("..") / ".." / "shared" / "data" / "g2o" / "intel.g2o"
if not path.is_file():
    path = Path("..") / "shared" / "data" / "g2o" / "intel.g2o"
if path.is_file() and not SMOKE:
    g = jp.read_g2o(path)
    prob = pose_graph_problem(g)
    s = jax.jit(lambda p: solve(p, linear_solver="sparse", stopping=default_stopping(200)))(prob)
    c = np.asarray(jax.jit(lambda p, v: marginals(p, v, "pose").covariances["pose"])(prob, s))
    xy = np.asarray(s.variables["pose"].data)
    fig, ax = plt.subplots(figsize=(7, 7))
    draw(ax, xy[:, :2], position_covariances("SE2", xy, c), every=5)
    ax.set_title("intel.g2o: 2σ position ellipses (every 5th pose)")
    plt.show()
else:
    print("skipped (smoke run, or ../shared/data not present)")
