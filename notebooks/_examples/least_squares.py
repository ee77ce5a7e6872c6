"""Second-order least squares with robust kernels, on arrays and on Lie groups.

``jaxpose.optim.least_squares(residual_fn, params, args, solver=LM(...))`` minimises
``0.5 · Σ ρ(rᵀ W r)`` over any pytree of Lie groups and arrays. This tutorial fits a curve
with Levenberg–Marquardt, compares robust kernels on data with outliers, averages SE(3)
poses with a Huber kernel, solves a whole batch of problems with ``vmap`` (each with its
own damping and stopping), differentiates through a solution (implicitly and unrolled),
and drives the iterations by hand with ``init``/``step``.

Run ``python notebooks/_examples/least_squares.py`` (``JAXPOSE_NOTEBOOK_SMOKE=1`` for tiny
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

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import jaxpose as jp
from jaxpose import optim

jax.config.update("jax_enable_x64", True)
SMOKE = os.environ.get("JAXPOSE_NOTEBOOK_SMOKE") == "1"  # tiny sizes (CI runs every notebook)
rng = np.random.default_rng(0)

# %% [markdown]
# ## A first fit: exponential decay
#
# The residual function takes `(params, args)` and returns any pytree of arrays; each leaf
# of shape `(*batch, d)` is a set of d-dimensional residual blocks. `verbose=True` prints
# one line per iteration from inside the compiled loop. Solves are usually wrapped in
# `jax.jit` (one compilation, then microseconds per call).

# %%
t = jnp.linspace(0.0, 2.0, 40)
y = 2.0 * jnp.exp(-1.3 * t) + 0.02 * jnp.asarray(rng.normal(size=40))


def decay(p, args):
    t, y = args
    return (p[0] * jnp.exp(-p[1] * t) - y)[:, None]  # 40 blocks of dimension 1


solve_decay = jax.jit(lambda p0: optim.least_squares(decay, p0, (t, y), verbose=True))
sol = solve_decay(jnp.array([1.0, 0.5]))
print("a, b =", sol.params, "| status", jp.Results.name_of(sol.status),
      "| steps", int(sol.num_steps), "| cost", float(sol.cost))

# %% [markdown]
# ## Robust kernels
#
# A line fit where a fifth of the points are gross outliers. The kernel ρ acts on each
# block's squared norm s = rᵀWr; FastTriggs (the default corrector, as in PyPose) turns it
# into iteratively reweighted least squares. `Triggs` also uses ρ'' (exact Gauss–Newton
# Hessian of the robust cost).

# %%
n_pts = 60
x = jnp.linspace(-3.0, 3.0, n_pts)
y_line = 0.7 * x - 0.4 + 0.05 * jnp.asarray(rng.normal(size=n_pts))
outliers = rng.random(n_pts) < 0.2
y_line = jnp.where(jnp.asarray(outliers), y_line + jnp.asarray(rng.uniform(3, 6, n_pts)), y_line)


def line(p, args):
    x, y = args
    return (p[0] * x + p[1] - y)[:, None]


kernels = {
    "none": None,
    "Huber": optim.Huber(0.3),
    "Cauchy": optim.Cauchy(0.3),
    "Tukey": optim.Tukey(1.0),
}
fit_line = jax.jit(lambda p0, kernel: optim.least_squares(line, p0, (x, y_line), kernel=kernel))
fits = {}
for name, kernel in kernels.items():
    # Tukey is non-convex: start it from the Huber fit, as one would in practice
    p0 = fits["Huber"] if name == "Tukey" else jnp.zeros(2)
    s = fit_line(p0, kernel)
    fits[name] = s.params
    print(f"{name:7s} slope {float(s.params[0]):+.3f}  intercept {float(s.params[1]):+.3f}"
          f"  ({int(s.num_steps)} steps)")

fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4))
ax0.plot(x, y_line, "k.", label="data")
for name, p in fits.items():
    ax0.plot(x, p[0] * x + p[1], label=name)
ax0.set_title("line fit with 20 % outliers")
ax0.legend()
s_grid = jnp.linspace(0.0, 9.0, 200)
for name, kernel in [("trivial", optim.Trivial()), ("Huber(1)", optim.Huber(1.0)),
                     ("Cauchy(1)", optim.Cauchy(1.0)), ("Tukey(1)", optim.Tukey(1.0)),
                     ("GemanMcClure(1)", optim.GemanMcClure(1.0))]:
    ax1.plot(s_grid, kernel(s_grid), label=name)
ax1.set_xlabel("s = rᵀWr")
ax1.set_ylabel("ρ(s)")
ax1.set_ylim(0, 9)
ax1.set_title("kernels")
ax1.legend()
plt.show()

# %% [markdown]
# ## Lie groups as parameters: robust pose averaging
#
# Parameters may be any pytree mixing groups and arrays; group leaves are updated by the
# right retraction `X ⊕ δ = X·Exp(δ)` and Jacobians are taken in the tangent space (6
# columns for an SE3, never the 7 stored numbers). Residual: `Log(X⁻¹·Zᵢ)` per measurement.

# %%
key = jax.random.PRNGKey(0)
k_true, k_noise, k_out = jax.random.split(key, 3)
X_true = jp.SE3.random(k_true)
m = 40
noise = jnp.concatenate([0.05 * jax.random.normal(k_noise, (m, 6)),
                         2.0 * jax.random.normal(k_out, (m // 4, 6))])  # 25 % outliers
Z = X_true @ jp.se3(noise).exp()


def pose_residual(params, Z):
    return Z.rminus(params["X"])  # (m, 6) blocks: Log(X⁻¹·Zᵢ)


@jax.jit
def average(delta):
    kernel = optim.Huber(delta)  # quadratic below δ²: a huge δ is plain least squares
    return optim.least_squares(pose_residual, {"X": jp.SE3.identity()}, Z, kernel=kernel)


for name, delta in (("none", 1e6), ("Huber(0.1)", 0.1)):
    s = average(delta)
    err = float(jnp.linalg.norm(s.params["X"].rminus(X_true)))
    print(f"kernel {name:10s}: distance to the true pose {err:.4f} ({int(s.num_steps)} steps)")

# %% [markdown]
# ## Strategies, solvers and linear solvers
#
# The damping strategy (PyPose's `Constant`, `Adaptive`, `TrustRegion` — the default — and
# Powell's `Dogleg`) and the linear solver (lineax `Cholesky`, `QR`, `LU`, `CG`, `SVD`)
# plug into `LevenbergMarquardt`; `GaussNewton` takes no damping. `Constant` damping cannot
# react to a rejected step, so it stops (DIVERGED) at the first one. Another start for the
# decay fit:

# %%
solvers = {
    "LM TrustRegion + Cholesky": optim.LM(),
    "LM Adaptive + QR": optim.LM(strategy=optim.Adaptive(damping=1e-3), linear_solver=optim.QR()),
    "LM Dogleg": optim.LM(strategy=optim.Dogleg()),
    "LM Constant(1e-2) + CG": optim.LM(strategy=optim.Constant(1e-2), linear_solver=optim.CG()),
    "Gauss-Newton + SVD": optim.GN(linear_solver=optim.SVD()),
}
for name, solver in solvers.items():
    run = jax.jit(lambda p0, solver=solver: optim.least_squares(decay, p0, (t, y), solver=solver))
    s = run(jnp.array([3.0, 0.2]))
    print(f"{name:27s} {jp.Results.name_of(s.status):10s} steps {int(s.num_steps):3d}"
          f"  cost {float(s.cost):.6f}")

# %% [markdown]
# ## A batch of problems with `vmap`
#
# The whole solve is one `lax.while_loop`, so `jax.vmap` solves many independent problems
# in one compiled program — each keeps its own damping, acceptance and stopping (PyPose
# shares one). Here: circles fitted to noisy arcs, one problem per circle.

# %%
n_problems = 50 if SMOKE else 1000
keys = jax.random.split(jax.random.PRNGKey(1), n_problems)


def make_arc(k):
    kc, kr, ka, kn = jax.random.split(k, 4)
    center = jax.random.uniform(kc, (2,), minval=-5, maxval=5)
    radius = jax.random.uniform(kr, (), minval=1, maxval=3)
    ang = jax.random.uniform(ka, (30,), minval=0, maxval=4.0)  # a partial arc
    pts = center + radius * jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)
    return pts + 0.01 * jax.random.normal(kn, pts.shape), jnp.append(center, radius)


def circle(p, pts):
    return (jnp.linalg.norm(pts - p[:2], axis=-1) - p[2])[:, None]


def fit(pts):
    p0 = jnp.append(pts.mean(0), 1.0)  # start at the centroid with unit radius
    return optim.least_squares(circle, p0, pts)


pts, truth = jax.vmap(make_arc)(keys)
batch = jax.jit(jax.vmap(fit))(pts)
err = jnp.abs(batch.params - truth).max(-1)
steps = f"{int(batch.num_steps.min())}..{int(batch.num_steps.max())}"
print(f"{n_problems} circles: {int(batch.converged.sum())} converged, {steps} steps per problem,"
      f" max error {float(err.max()):.3f}")

# %% [markdown]
# ## Differentiating through the solution
#
# `adjoint="implicit"` (default) differentiates the optimum by the implicit function
# theorem — one linear solve in the backward pass, independent of the iteration count;
# `adjoint="unrolled"` backpropagates through the iterations. Both agree with finite
# differences. Here: how the fitted decay rate moves with the measurements' time scale.

# %%
def fitted_rate(scale, adjoint):
    s = optim.least_squares(decay, jnp.array([1.0, 0.5]), (scale * t, y), adjoint=adjoint)
    return s.params[1]


grad_rate = jax.jit(jax.grad(fitted_rate), static_argnums=1)
g_impl, g_unr = grad_rate(1.0, "implicit"), grad_rate(1.0, "unrolled")
h = 1e-5
rate = jax.jit(fitted_rate, static_argnums=1)
g_fd = (rate(1.0 + h, "implicit") - rate(1.0 - h, "implicit")) / (2 * h)
print(f"d rate / d scale: implicit {float(g_impl):.8f}  unrolled {float(g_unr):.8f}"
      f"  finite differences {float(g_fd):.8f}")

# %% [markdown]
# ## Driving the iterations by hand
#
# Like PyPose's `optimizer.step()`, a solver exposes `init` and `step` on a state (the first
# `step` only linearises). `stop=StopOnPlateau(...)` gives PyPose's scheduler semantics
# inside `least_squares`.

# %%
solver = optim.LM()
state = solver.init(decay, jnp.array([1.0, 0.5]), (t, y))
step = jax.jit(lambda state: solver.step(decay, state, (t, y)))
costs = [float(state.cost)]
for _ in range(8):
    state = step(state)
    costs.append(float(state.cost))
print("cost per step:", np.round(costs, 6))
rule = optim.StopOnPlateau(steps=50, patience=2, decreasing=1e-6)
plateau = jax.jit(lambda p0: optim.least_squares(decay, p0, (t, y), stop=rule))(jnp.ones(2))
print("StopOnPlateau:", jp.Results.name_of(plateau.status), int(plateau.num_steps), "steps")
