"""MPC imitation learning (Amos et al. 2018, Sec. 5.1; PyPose's MPC example).

An expert controls a linear system ``x⁺ = A* x + B* u`` with MPC (quadratic cost Q, p,
horizon T). A learner with its own (A, B) runs the same MPC and is trained so that its
planned states and controls match the expert's from random initial states (batch of 4),
by gradients through the MPC solution (implicit differentiation or unrolling). The model
loss ``mean((A − A*)²) + mean((B − B*)²)`` measures recovery of the expert's dynamics.

Run ``python notebooks/_examples/mpc_imitation.py [--steps N] [--gradient unroll]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any, NamedTuple

if __package__ in (None, ""):
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

import jax
import jax.numpy as jnp
import optax

from jaxpose.control import MPC, QuadraticCost
from jaxpose.dynamics import LTI


class Expert(NamedTuple):
    A: jax.Array
    B: jax.Array
    Q: jax.Array
    p: jax.Array


def make_expert(key: jax.Array, n_state: int = 3, n_ctrl: int = 3, dtype: Any = None) -> Expert:
    """Expert as in the seed paper: A = I + 0.2·N(0,1), B ~ N(0,1), Q = I, p ~ N(0,1)."""
    dtype = dtype or jnp.result_type(float)
    ka, kb, kp = jax.random.split(key, 3)
    A = jnp.eye(n_state, dtype=dtype) + 0.2 * jax.random.normal(ka, (n_state, n_state), dtype)
    B = jax.random.normal(kb, (n_state, n_ctrl), dtype)
    Q = jnp.eye(n_state + n_ctrl, dtype=dtype)
    p = jax.random.normal(kp, (n_state + n_ctrl,), dtype)
    return Expert(A, B, Q, p)


def plan(
    A: jax.Array, B: jax.Array, expert: Expert, x0: jax.Array, T: int, gradient: str = "implicit"
) -> tuple[jax.Array, jax.Array]:
    """MPC plan (x (…, T+1, n), u (…, T, m)) of the model (A, B) under the expert's cost."""
    mpc = MPC(LTI(A, B), QuadraticCost(expert.Q, expert.p), T, gradient=gradient)
    sol = mpc(x0)
    return sol.x, sol.u


def traj_loss(
    params: tuple[jax.Array, jax.Array],
    expert: Expert,
    x0: jax.Array,
    T: int,
    gradient: str = "implicit",
) -> jax.Array:
    """Imitation loss: mean squared difference of planned controls and states."""
    A, B = params
    x_true, u_true = plan(expert.A, expert.B, expert, x0, T, gradient)
    x_pred, u_pred = plan(A, B, expert, x0, T, gradient)
    return jnp.mean((u_true - u_pred) ** 2) + jnp.mean((x_true - x_pred) ** 2)


def model_loss(params: tuple[jax.Array, jax.Array], expert: Expert) -> jax.Array:
    A, B = params
    return jnp.mean((A - expert.A) ** 2) + jnp.mean((B - expert.B) ** 2)


class History(NamedTuple):
    traj_loss: jax.Array
    model_loss: jax.Array
    A: jax.Array
    B: jax.Array
    expert: Expert


def train(
    n_state: int = 3,
    n_ctrl: int = 3,
    T: int = 5,
    batch: int = 4,
    steps: int = 3000,
    lr: float = 3e-2,
    seed: int = 0,
    gradient: str = "implicit",
) -> History:
    """Learn (A, B) from the expert's MPC plans with Adam (cosine-decayed ``lr``); the
    whole loop is one ``lax.scan``. Returns the loss histories and the learned A, B."""
    k_exp, k_init, k_data = jax.random.split(jax.random.PRNGKey(seed), 3)
    expert = make_expert(k_exp, n_state, n_ctrl)
    ka, kb = jax.random.split(k_init)
    A0 = jnp.eye(n_state) + 0.2 * jax.random.normal(ka, (n_state, n_state))
    B0 = jax.random.normal(kb, (n_state, n_ctrl))
    schedule = optax.cosine_decay_schedule(lr, steps, alpha=1e-2)
    opt = optax.adam(schedule)
    params = (A0, B0)
    state = opt.init(params)
    grad_fn = jax.value_and_grad(traj_loss)

    def step(carry: Any, key: jax.Array):
        params, state = carry
        x0 = jax.random.normal(key, (batch, n_state))
        loss, g = grad_fn(params, expert, x0, T, gradient)
        updates, state = opt.update(g, state, params)
        params = optax.apply_updates(params, updates)
        return (params, state), (loss, model_loss(params, expert))

    keys = jax.random.split(k_data, steps)
    run = jax.jit(lambda p, s, k: jax.lax.scan(step, (p, s), k))
    (params, _), (tl, ml) = run(params, state, keys)
    ml = jnp.concatenate([model_loss((A0, B0), expert)[None], ml])
    return History(tl, ml, params[0], params[1], expert)


def plot(hist: History, path: str | None = None) -> None:  # pragma: no cover - optional
    """Model and trajectory loss curves (needs matplotlib)."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3))
    ax[0].semilogy(hist.model_loss)
    ax[0].set(title="model loss", xlabel="iteration")
    ax[1].semilogy(hist.traj_loss)
    ax[1].set(title="trajectory (imitation) loss", xlabel="iteration")
    fig.tight_layout()
    if path:
        fig.savefig(path)


def main(argv: list[str] | None = None) -> History:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--gradient", choices=("implicit", "unroll"), default="implicit")
    ap.add_argument("--plot", type=str, default=None, help="save loss curves to this file")
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    hist = train(steps=args.steps, gradient=args.gradient)
    dt = time.perf_counter() - t0
    ml = hist.model_loss
    print(f"{args.steps} steps in {dt:.1f} s (incl. compile), gradient={args.gradient}")
    print(
        f"model loss {float(ml[0]):.3e} → {float(ml[-1]):.3e} (×{float(ml[0] / ml[-1]):.1e} lower)"
    )
    print(f"trajectory loss {float(hist.traj_loss[0]):.3e} → {float(hist.traj_loss[-1]):.3e}")
    if args.plot:
        plot(hist, args.plot)
    return hist


if __name__ == "__main__":
    main()
