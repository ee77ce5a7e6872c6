"""Cart-pole swing-up with iLQR and box force limits.

The pole starts hanging down (θ = π) and must end upright (θ = 0) with the cart back at
the origin, with the force limited to ``|F| ≤ u_max``. iLQR (``jaxpose.control.ilqr``)
handles the limits by projected Newton in the backward pass and clipping in the forward
pass, so the returned controls always satisfy them. Receding-horizon use of the same
problem is :class:`jaxpose.control.MPC`.

Run ``python notebooks/_examples/cartpole_ilqr.py [--horizon 80] [--u-max 5]``.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time
from typing import Any

if __package__ in (None, ""):
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

import jax
import jax.numpy as jnp

from jaxpose import Results
from jaxpose.control import FunctionCost, ILQRSolution, ilqr
from jaxpose.dynamics import CartPole


def swing_up_cost(
    stage_weight: float = 0.1, control_weight: float = 0.01, terminal_weight: float = 100.0
) -> FunctionCost:
    """Small running cost on the state (1 − cos θ for the angle) and the force; a large
    terminal cost on reaching the upright rest state at the origin."""

    def stage(x: jax.Array, u: jax.Array, t: Any) -> jax.Array:
        s = x[0] ** 2 + 0.1 * x[1] ** 2 + 2.0 * (1.0 - jnp.cos(x[2])) + 0.1 * x[3] ** 2
        return 0.5 * stage_weight * s + 0.5 * control_weight * u[0] ** 2

    def terminal(x: jax.Array) -> jax.Array:
        s = x[0] ** 2 + x[1] ** 2 + 2.0 * (1.0 - jnp.cos(x[2])) + x[3] ** 2
        return 0.5 * terminal_weight * s

    return FunctionCost(stage, terminal)


@functools.lru_cache(maxsize=8)
def _solver(horizon: int, dt: float, tol: float) -> Any:
    """One compiled solver per (horizon, dt, tol); x0, u_max and max_iter are traced."""
    model, cost = CartPole(dt=dt), swing_up_cost()
    u0 = jnp.full((horizon, 1), 0.1)  # breaks the symmetry of the hanging equilibrium

    def run(x0: jax.Array, u_max: jax.Array, max_iter: jax.Array) -> ILQRSolution:
        return ilqr(model, cost, x0, u0, u_lower=-u_max, u_upper=u_max, max_iter=max_iter, tol=tol)

    return jax.jit(run)


def solve(
    horizon: int = 80,
    dt: float = 0.05,
    u_max: float = 5.0,
    max_iter: int = 400,
    tol: float = 1e-7,
    x0: Any = None,
) -> tuple[ILQRSolution, CartPole]:
    """Swing-up (default ``x0``: at rest hanging down); returns the iLQR solution and the
    model."""
    x0 = jnp.array([0.0, 0.0, jnp.pi, 0.0]) if x0 is None else jnp.asarray(x0)
    sol = _solver(horizon, float(dt), float(tol))(
        x0, jnp.asarray(u_max, x0.dtype), jnp.asarray(max_iter)
    )
    return sol, CartPole(dt=dt)


def plot(sol: ILQRSolution, dt: float, path: str | None = None) -> None:  # pragma: no cover
    """States and force over time (needs matplotlib)."""
    import matplotlib.pyplot as plt

    t = jnp.arange(sol.x.shape[0]) * dt
    fig, ax = plt.subplots(1, 3, figsize=(11, 3))
    ax[0].plot(t, sol.x[:, 0], label="cart x")
    ax[0].plot(t, sol.x[:, 2], label="pole θ")
    ax[0].legend()
    ax[1].plot(t, sol.x[:, 1], label="ẋ")
    ax[1].plot(t, sol.x[:, 3], label="θ̇")
    ax[1].legend()
    ax[2].step(t[:-1], sol.u[:, 0], where="post")
    ax[2].set(title="force (limited)")
    fig.tight_layout()
    if path:
        fig.savefig(path)


def main(argv: list[str] | None = None) -> ILQRSolution:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--horizon", type=int, default=80)
    ap.add_argument("--dt", type=float, default=0.05)
    ap.add_argument("--u-max", type=float, default=5.0)
    ap.add_argument("--max-iter", type=int, default=400)
    ap.add_argument("--plot", type=str, default=None)
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    sol, _ = solve(args.horizon, args.dt, args.u_max, args.max_iter)
    jax.block_until_ready(sol)
    print(
        f"iLQR: {Results.name_of(sol.status)} after {int(sol.iterations)} iterations "
        f"({time.perf_counter() - t0:.1f} s incl. compile), cost {float(sol.cost):.4f}"
    )
    print(f"final state [x, ẋ, θ, θ̇] = {[round(float(v), 4) for v in sol.x[-1]]}")
    print(f"force range [{float(sol.u.min()):.3f}, {float(sol.u.max()):.3f}] (limit ±{args.u_max})")
    if args.plot:
        plot(sol, args.dt, args.plot)
    return sol


if __name__ == "__main__":
    main()
