"""EKF vs UKF vs particle filter on a kinematic bicycle (Monte-Carlo consistency).

The bicycle (state ``[px, py, ψ, v]``, inputs ``[a, δ]``) drives a smooth curve through a
20 m × 20 m square with four range beacons at the corners; it measures the ranges and its
speed. Each Monte-Carlo run draws the initial state from the prior and simulates process
and measurement noise; the three filters run on the same data. Reported per filter:

* RMSE of position, heading and speed over all runs and steps;
* average NEES (normalised estimation error squared) ``eᵀ P⁻¹ e`` over runs, per step:
  a consistent filter has ANEES ≈ n = 4; with R runs the two-sided 95 % band is
  ``[χ²_{0.025}(R·n), χ²_{0.975}(R·n)] / R`` (Bar-Shalom et al. 2001).

Run ``python notebooks/_examples/bicycle_filters.py [--runs 100] [--steps 100]``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from typing import Any, NamedTuple

if __package__ in (None, ""):
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

import jax
import jax.numpy as jnp
import numpy as np

from jaxpose.dynamics import Bicycle
from jaxpose.filters import EKF, UKF, ParticleFilter

FILTERS = ("EKF", "UKF", "PF")


class Setup(NamedTuple):
    model: Bicycle
    x0: jax.Array  # prior mean
    P0: jax.Array
    Q: jax.Array
    R: jax.Array
    us: jax.Array  # (steps, 2)


def make_setup(steps: int = 100, dtype: Any = None) -> Setup:
    """Model, prior, noise levels and the input sequence (a gentle S-curve)."""
    dtype = dtype or jnp.result_type(float)
    model = Bicycle(dt=0.1)
    t = jnp.arange(steps, dtype=dtype) * 0.1
    us = jnp.stack([0.3 * jnp.sin(0.5 * t), 0.15 * jnp.sin(0.3 * t)], -1)
    x0 = jnp.array([5.0, 5.0, 0.3, 2.0], dtype)
    P0 = jnp.diag(jnp.array([0.3, 0.3, 0.05, 0.2], dtype) ** 2)
    Q = jnp.diag(jnp.array([0.02, 0.02, 0.005, 0.05], dtype) ** 2)
    R = jnp.diag(jnp.array([0.3, 0.3, 0.3, 0.3, 0.1], dtype) ** 2)
    return Setup(model, x0, P0, Q, R, us.astype(dtype))


def simulate(key: jax.Array, s: Setup, runs: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``runs`` data sets: true initial states (runs, 4), true states (runs, steps, 4)
    and measurements (runs, steps, 5). All noise is drawn by one ``normal`` call (cheap
    to compile), then the runs are simulated by a vmapped ``lax.scan``."""
    n, p = s.Q.shape[0], s.R.shape[0]
    steps = s.us.shape[0]
    z = jax.random.normal(key, (runs, steps + 1, n + p), s.P0.dtype)
    x_init = s.x0 + z[:, 0, :n] @ jnp.linalg.cholesky(s.P0).T
    w = z[:, 1:, :n] @ jnp.linalg.cholesky(s.Q).T
    v = z[:, 1:, n:] @ jnp.linalg.cholesky(s.R).T

    def one(x0: jax.Array, w: jax.Array, v: jax.Array) -> tuple[jax.Array, jax.Array]:
        def step(x: jax.Array, inp: tuple[jax.Array, ...]):
            u, wt, vt, t = inp
            x = s.model.state_transition(x, u, t) + wt
            return x, (x, s.model.observation(x, u, t) + vt)

        _, (xs, ys) = jax.lax.scan(step, x0, (s.us, w, v, jnp.arange(steps)))
        return xs, ys

    xs, ys = jax.vmap(one)(x_init, w, v)
    return x_init, xs, ys


class MonteCarlo(NamedTuple):
    truth: jax.Array  # (runs, steps, 4)
    est: dict[str, jax.Array]  # filter → (runs, steps, 4)
    cov: dict[str, jax.Array]  # filter → (runs, steps, 4, 4)
    nees: dict[str, jax.Array]  # filter → (runs, steps)


def monte_carlo(
    runs: int = 100,
    steps: int = 100,
    num_particles: int = 1000,
    seed: int = 0,
    filters: tuple[str, ...] = FILTERS,
) -> MonteCarlo:
    """Run every filter on ``runs`` simulated data sets (vmapped, jitted). The particle
    filter draws from ``rbg`` keys (much cheaper to compile than threefry on CPU)."""
    s = make_setup(steps)
    flt = {
        "EKF": EKF(s.model, s.Q, s.R),
        "UKF": UKF(s.model, s.Q, s.R),
        "PF": ParticleFilter(s.model, s.Q, s.R, num_particles=num_particles),
    }

    def run_all(seed: jax.Array) -> tuple[jax.Array, dict[str, Any], dict[str, Any]]:
        truth_key = jax.random.fold_in(jax.random.PRNGKey(0), seed)
        _, truth, ys = simulate(truth_key, s, runs)
        pf_keys = jax.random.split(jax.random.key(seed, impl="rbg"), runs)
        est, cov = {}, {}
        for name in filters:
            if name == "PF":
                run = lambda k, y: flt["PF"].run(k, s.x0, s.P0, y, s.us)[0]
                res = jax.vmap(run)(pf_keys, ys)
            else:
                res = jax.vmap(lambda y, f=flt[name]: f.run(s.x0, s.P0, y, s.us))(ys)
            est[name], cov[name] = res.x, res.P
        return truth, est, cov

    truth, est, cov = jax.jit(run_all)(jnp.asarray(seed, jnp.uint32))
    nees = {}
    for name in filters:
        e = truth - est[name]
        nees[name] = jnp.einsum("rti,rti->rt", e, jnp.linalg.solve(cov[name], e[..., None])[..., 0])
    return MonteCarlo(truth, est, cov, nees)


def chi2_band(dof: int, runs: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` band of the run-averaged NEES (Wilson–Hilferty χ² quantiles)."""
    z = _normal_quantile(0.5 + prob / 2)
    k = dof * runs

    def q(zz: float) -> float:
        return k * (1 - 2 / (9 * k) + zz * math.sqrt(2 / (9 * k))) ** 3 / runs

    return q(-z), q(z)


def _normal_quantile(p: float) -> float:
    # Acklam-free: bisection on erf (adequate for a test band).
    lo, hi = -10.0, 10.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if 0.5 * (1 + math.erf(mid / math.sqrt(2))) < p:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def summary(mc: MonteCarlo) -> dict[str, dict[str, float]]:
    """RMSE (position, heading, speed), mean ANEES and the fraction of steps whose
    ANEES lies inside the 95 % band, per filter."""
    runs = mc.truth.shape[0]
    lo, hi = chi2_band(mc.truth.shape[-1], runs)
    out = {}
    for name, est in mc.est.items():
        e = np.asarray(mc.truth - est)
        anees = np.asarray(mc.nees[name]).mean(0)
        out[name] = {
            "rmse_pos": float(np.sqrt(np.mean(np.sum(e[..., :2] ** 2, -1)))),
            "rmse_heading": float(np.sqrt(np.mean(e[..., 2] ** 2))),
            "rmse_speed": float(np.sqrt(np.mean(e[..., 3] ** 2))),
            "anees": float(anees.mean()),
            "in_band": float(np.mean((anees >= lo) & (anees <= hi))),
        }
    return out


def format_summary(stats: dict[str, dict[str, float]], runs: int) -> str:
    lo, hi = chi2_band(4, runs)
    lines = [
        f"{'filter':6s} {'RMSE pos [m]':>12s} {'ψ [rad]':>9s} {'v [m/s]':>9s} "
        f"{'ANEES':>7s} {'in 95% band':>12s}   (n = 4, band [{lo:.2f}, {hi:.2f}])"
    ]
    for name, s in stats.items():
        lines.append(
            f"{name:6s} {s['rmse_pos']:12.4f} {s['rmse_heading']:9.4f} "
            f"{s['rmse_speed']:9.4f} {s['anees']:7.2f} {s['in_band']:12.0%}"
        )
    return "\n".join(lines)


def ellipse(P2: np.ndarray, center: np.ndarray, k: float = 2.0, num: int = 64) -> np.ndarray:
    """Points (num, 2) of the k-sigma ellipse of a 2×2 covariance."""
    w, V = np.linalg.eigh(P2)
    t = np.linspace(0, 2 * np.pi, num)
    circle = np.stack([np.cos(t), np.sin(t)], -1)
    return center + k * (circle * np.sqrt(np.maximum(w, 0))) @ V.T


def plot(
    mc: MonteCarlo, run: int = 0, every: int = 10, path: str | None = None
) -> None:  # pragma: no cover - optional
    """Trajectory of one run with 2σ position ellipses, and ANEES per step."""
    import matplotlib.pyplot as plt

    s = make_setup(mc.truth.shape[1])
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.5))
    ax[0].plot(*np.asarray(mc.truth[run, :, :2]).T, "k-", label="truth")
    ax[0].plot(*np.asarray(s.model.landmarks).T, "k^", label="beacons")
    for name, c in zip(mc.est, ("C0", "C1", "C2")):
        est, cov = np.asarray(mc.est[name][run]), np.asarray(mc.cov[name][run])
        ax[0].plot(est[:, 0], est[:, 1], c + "--", label=name)
        for t in range(0, est.shape[0], every):
            ax[0].plot(*ellipse(cov[t, :2, :2], est[t, :2]).T, c, lw=0.8)
    ax[0].set_aspect("equal")
    ax[0].legend()
    lo, hi = chi2_band(4, mc.truth.shape[0])
    for name in mc.nees:
        ax[1].plot(np.asarray(mc.nees[name]).mean(0), label=name)
    ax[1].axhspan(lo, hi, color="0.9", label="95% band")
    ax[1].set(xlabel="step", ylabel="ANEES")
    ax[1].legend()
    fig.tight_layout()
    if path:
        fig.savefig(path)


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--particles", type=int, default=1000)
    ap.add_argument("--plot", type=str, default=None)
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    mc = monte_carlo(args.runs, args.steps, args.particles)
    stats = summary(mc)
    print(
        f"{args.runs} Monte-Carlo runs × {args.steps} steps, PF with {args.particles} "
        f"particles ({time.perf_counter() - t0:.1f} s incl. compile)"
    )
    print(format_summary(stats, args.runs))
    if args.plot:
        plot(mc, path=args.plot)
    return stats


if __name__ == "__main__":
    main()
