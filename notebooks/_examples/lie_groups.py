"""Lie groups, their algebras and tangent-space calculus in jaxpose.

What this tutorial covers: creating group elements (PyPose's storage layouts), composing
them and acting on points with broadcasting batch axes, ``Exp``/``Log`` and the Jacobians
of every algebra (checked against autodiff), derivatives that stay finite at θ = 0 and
θ = π, conversions (matrices, Euler angles, quaternion orders, jaxlie / PyPose), odometry
chaining with ``cumprod``, and optimisation on the manifold with optax.

Run ``python notebooks/_examples/lie_groups.py`` (``JAXPOSE_NOTEBOOK_SMOKE=1`` for tiny sizes).
"""

from __future__ import annotations

import os
import sys

if __package__ in (None, ""):
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

# %% [markdown]
# ## Set-up
#
# Every group element is an `equinox.Module` (a pytree) holding one array `data` of shape
# `(*batch, storage_dim)`. We switch on float64 to show the library's accuracy; everything
# below also runs in float32. `SMOKE` shrinks the sizes when CI executes the notebook.

# %%
import importlib.util
import os
import time

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import optax

import jaxpose as jp
from jaxpose import interop

jax.config.update("jax_enable_x64", True)
SMOKE = os.environ.get("JAXPOSE_NOTEBOOK_SMOKE") == "1"
key = jax.random.PRNGKey(0)

# %% [markdown]
# ## Elements and storage layouts
#
# The layouts are PyPose's: quaternions are stored scalar-last `[qx, qy, qz, qw]`, SE3 is
# `[t, q]`, and tangent vectors put the translation part first (`se3 = [ρ, φ]`).

# %%
R = jp.so3(jnp.array([0.0, 0.0, jnp.pi / 2])).exp()  # 90° about z
T = jp.SE3(jnp.array([1.0, 2.0, 3.0, *R.data]))  # [tx, ty, tz, qx, qy, qz, qw]
print("SO3 data [qx, qy, qz, qw]:", R.data)
print("SE3 data:", T.data, "| batch shape", T.shape)
print("rotate x-axis:", R @ jnp.array([1.0, 0.0, 0.0]))
print("transform the origin:", T @ jnp.zeros(3))
print("4x4 matrix:\n", T.matrix())
for G in jp.GROUPS:
    print(f"{G.__name__:6s} storage {G.storage_dim}  tangent {G.tangent_dim}  layout {G.layout}")

# %% [markdown]
# ## Batches broadcast like numpy
#
# `X @ Y` composes, `X @ p` acts on points (3-vectors or homogeneous 4-vectors). Batch axes
# broadcast: a (4, 1) batch composed with a (1, 3) batch gives a (4, 3) batch.

# %%
k1, k2, k3 = jax.random.split(key, 3)
X = jp.SE3.random(k1, (4, 1))
Y = jp.SE3.random(k2, (1, 3))
Z = X @ Y
print("composed batch shape:", Z.shape, "| data shape:", Z.data.shape)
pts = jax.random.normal(k3, (4, 3, 3))
print("points moved:", (Z @ pts).shape)
err = jnp.abs((X @ (Y @ pts)) - (Z @ pts)).max()
print(f"associativity of the action: max error {float(err):.1e}")

# %% [markdown]
# ## Exp, Log and the Jacobians of every algebra
#
# The right Jacobian satisfies `Exp(a + δ) ≈ Exp(a)·Exp(Jr(a)·δ)`, so it equals the
# derivative of `Log(Exp(a)⁻¹·Exp(a + δ))` at δ = 0. We check that with `jax.jacfwd` for
# the algebras, and the adjoint identity `X·Exp(a) = Exp(Adj(X)·a)·X`.

# %%
GROUPS = (jp.SO3, jp.SE3, jp.SE2) if SMOKE else jp.GROUPS  # compiling all six takes a while


def identities(G, key):
    """Max |Jr − autodiff|, |Jr·Jr⁻¹ − I| and adjoint-identity error for group G."""
    ka, kx = jax.random.split(key)
    a = 0.7 * jax.random.normal(ka, (G.tangent_dim,))
    A = G.algebra(a)
    local = lambda d: (G.exp(a).inv() @ G.exp(a + d)).log().data
    jr_autodiff = jax.jacfwd(local)(jnp.zeros_like(a))
    Xg = G.random(kx)
    adj_err = (Xg @ A.exp()).data - (Xg.adj(A).exp() @ Xg).data
    return (
        jnp.abs(A.jr() - jr_autodiff).max(),
        jnp.abs(A.jr() @ A.jr_inv() - jnp.eye(G.tangent_dim)).max(),
        jnp.abs(adj_err).max(),
    )


for G in GROUPS:
    e_jr, e_inv, e_adj = jax.jit(identities, static_argnums=0)(G, key)
    print(f"{G.__name__:6s} |Jr − autodiff| {e_jr:.1e}  |Jr·Jr⁻¹ − I| {e_inv:.1e}", end="")
    print(f"  adjoint identity {e_adj:.1e}")

# %% [markdown]
# ## Derivatives stay finite at θ = 0 and θ = π
#
# Small-angle series switch where they are exact to the dtype's precision, and every
# branch uses the double-`where` pattern, so values and derivatives of any order are
# NaN-free (the test suite checks up to third derivatives; see the numerics page of the
# documentation). Gradient and Hessian of a function of `Log(Exp(φ))` and `Jr(φ)`:

# %%
def f(phi):
    return jp.so3(phi).exp().log().data.sum() + jp.so3(phi).jr().sum()


points = jnp.array([[0.0, 0.0, 0.0], [1e-8, 0.0, 0.0], [0.0, 0.0, jnp.pi]])
grads, hessians = jax.jit(jax.vmap(lambda p: (jax.grad(f)(p), jax.hessian(f)(p))))(points)
for name, g, h in zip(("θ = 0", "θ = 1e-8", "θ = π"), grads, hessians):
    finite = bool(jnp.all(jnp.isfinite(g)) & jnp.all(jnp.isfinite(h)))
    print(f"{name:9s} gradient {np.round(np.asarray(g), 6)}  gradient and Hessian finite: {finite}")

# %% [markdown]
# ## Conversions
#
# Rotation matrices (`from_matrix` checks orthogonality, `check=False` projects instead),
# roll-pitch-yaw Euler angles (`R = Rz(y)·Ry(p)·Rx(r)`), scalar-first quaternions, and the
# peers through `jaxpose.interop` when they are installed.

# %%
@jax.jit
def conversions(R):
    M = R.matrix()
    e = R.euler()
    return {
        "matrix round trip": jnp.abs(jp.SO3.from_matrix(M).matrix() - M).max(),
        "euler round trip": jnp.abs(jp.from_euler(e).matrix() - M).max(),
        "euler [r, p, y]": e[0],
        "wxyz": R.wxyz()[0],
        "stored xyzw": R.data[0],
    }


for name, value in conversions(jp.SO3.random(key, (2,))).items():
    print(f"{name}: {value}")
if importlib.util.find_spec("jaxlie"):
    J = interop.to_jaxlie(T)  # jaxlie stores [qw, qx, qy, qz, tx, ty, tz]
    print("jaxlie:", J, "| back to jaxpose:", interop.from_jaxlie(J).data)
else:
    print("jaxlie not installed: skipping the jaxlie conversion")
if importlib.util.find_spec("pypose"):
    print("PyPose:", interop.to_pypose(T))  # same storage layout, no reordering
else:
    print("pypose not installed: skipping the PyPose conversion")

# %% [markdown]
# ## Chaining odometry with `cumprod`
#
# Relative motions `Δᵢ` chain into absolute poses `Xᵢ = Δ₀·Δ₁·…·Δᵢ` with
# `cumprod(axis=0, left=False)` — a parallel `jax.lax.associative_scan`, not a Python loop.
# Here a robot drives forward while yawing; noise on the increments makes the estimate drift.

# %%
n = 50 if SMOKE else 400
step = jnp.array([0.1, 0.0, 0.0, 0.0, 0.0, 2 * jnp.pi / n * 1.5])  # [ρ, φ]: forward + yaw


@jax.jit
def odometry(noise):
    deltas = jp.se3(jnp.broadcast_to(step, noise.shape)).exp()
    poses = deltas.cumprod(axis=0, left=False)
    noisy = (deltas @ jp.se3(noise).exp()).cumprod(axis=0, left=False)
    mid = jp.SE3.identity().interpolate(poses[-1], 0.5)  # geodesic half-way point
    return poses.translation(), noisy.translation(), mid.translation()


noise = 0.003 * jax.random.normal(jax.random.PRNGKey(1), (n, 6))
true_path, drift_path, mid = odometry(noise)
fig, ax = plt.subplots(figsize=(5, 5))
ax.plot(true_path[:, 0], true_path[:, 1], label="noise-free increments")
ax.plot(drift_path[:, 0], drift_path[:, 1], label="noisy increments")
ax.plot(mid[0], mid[1], "k*", ms=10, label="geodesic midpoint start→end")
ax.set_aspect("equal")
ax.legend()
plt.show()

# %% [markdown]
# ## Batched throughput under `jit` + `vmap`
#
# Everything is a pure function of arrays, so `jax.jit` compiles whole batched pipelines.
# f2 = Log(Exp(x)·Exp(y)) on so3 and its per-element Jacobian (the seed paper's benchmark).

# %%
B = 1_000 if SMOKE else 100_000
x = 0.5 * jax.random.normal(jax.random.PRNGKey(2), (B, 3))
y = 0.5 * jax.random.normal(jax.random.PRNGKey(3), (B, 3))
f2 = jax.jit(lambda x, y: (jp.so3(x).exp() @ jp.so3(y).exp()).log().data)
jac_f2 = jax.jit(jax.vmap(jax.jacfwd(lambda x, y: (jp.so3(x).exp() @ jp.so3(y).exp()).log().data)))
for name, fn in (("f2", f2), ("f2 Jacobian", jac_f2)):
    fn(x, y).block_until_ready()  # compile
    t0 = time.perf_counter()
    fn(x, y).block_until_ready()
    dt = time.perf_counter() - t0
    print(f"{name:12s} batch {B}: {B / dt:.2e} op/s")

# %% [markdown]
# ## Optimisation on the manifold with optax
#
# `jp.manifold` takes gradients in the tangent space (right perturbation `X ⊕ δ = X·Exp(δ)`)
# of any pytree mixing groups and arrays, and `optax_on_manifold` runs any optax optimizer on
# such pytrees. Here Adam finds the rotation average (Karcher mean) of noisy rotations.

# %%
truth = jp.SO3.random(jax.random.PRNGKey(4))
samples = truth @ jp.so3(0.2 * jax.random.normal(jax.random.PRNGKey(5), (64, 3))).exp()


def loss(params):
    return jnp.mean(jnp.sum(samples.rminus(params["R"]) ** 2, -1))


opt = jp.manifold.optax_on_manifold(optax.adam(5e-2))
params = {"R": jp.SO3.identity()}
state = opt.init(params)


@jax.jit
def adam_step(params, state):
    value, g = jp.manifold.value_and_grad(loss)(params)
    updates, state = opt.update(g, state, params)
    return opt.apply_updates(params, updates), state, value


losses = []
for _ in range(60 if SMOKE else 300):
    params, state, value = adam_step(params, state)
    losses.append(float(value))
angle = float(jnp.linalg.norm(params["R"].rminus(truth)))
print(f"final loss {losses[-1]:.4f}; estimate is {angle:.3f} rad from the true rotation")
plt.semilogy(losses)
plt.xlabel("Adam step")
plt.ylabel("mean squared geodesic distance")
plt.show()
