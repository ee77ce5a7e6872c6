"""Learning a pendulum's damping and mass from MuJoCo MJX rollouts through an EKF.

A MuJoCo pendulum (MJCF written inline, simulated by MJX) swings under random torques and
its angle is measured with noise. The learner's model is the same MJX pendulum wrapped as
a jaxpose System (``jaxpose.dynamics.mjx.MJXSystem``) whose hinge damping and pole mass are
unknown. jaxpose's EKF runs over the measured sequences, linearising MuJoCo's step by
forward-mode autodiff, and its innovations ``r = y − h(x⁻)`` with covariances
``S = H P⁻ Hᵀ + R`` give the negative log-likelihood of the data (prediction-error method)

    NLL(θ) = ½ Σₖ rₖᵀ Sₖ⁻¹ rₖ + log det Sₖ,

which Adam minimises over θ = log(damping, mass) by gradients through the filter and
MuJoCo's dynamics: forward mode (``jax.jacfwd``, two parameters; the reverse mode gives the
same numbers but compiles about twice as long through the EKF's own forward-mode
linearisation). The whole training loop (filter over a batch of sequences, gradient, Adam
update) is one jitted ``lax.scan``. The mass is identifiable through the response to the
applied torque, the damping through the decay of the swing. ``--filter ukf`` scores the
data with jaxpose's UKF instead (sigma points through MJX; no Jacobians).

Run ``python notebooks/_examples/mjx_learning.py [--steps N] [--filter ekf|ukf]
[--plot FILE]`` (needs ``pip install 'jaxpose[mjx]'``: mujoco and mujoco-mjx).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any, NamedTuple

if __package__ in (None, ""):
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxpose.dynamics import rollout
from jaxpose.dynamics.mjx import MJXSystem
from jaxpose.filters import EKF, UKF

# A 1-m capsule pole on a hinge, driven by a torque motor; y-axis hinge, θ = 0 hangs down.
PENDULUM_XML = """
<mujoco model="pendulum">
  <option timestep="0.01" integrator="Euler"/>
  <worldbody>
    <body name="pole">
      <joint name="hinge" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0 0 -1" size="0.04" mass="1"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="hinge" gear="1" ctrllimited="false"/>
  </actuator>
</mujoco>
"""
POLE = 1  # body id of the pole (0 is the world)
TRUE = {"damping": 0.4, "mass": 1.6}
GUESS = {"damping": 0.05, "mass": 0.6}
NOISE = 0.02  # rad, angle measurement noise (std)


def bind(model: Any, params: dict[str, jax.Array]) -> Any:
    """Apply ``{"damping", "mass"}`` to the MJX model. The pole's inertia scales with its
    mass (same shape, uniform density), so the whole rigid body changes consistently."""
    scale = params["mass"] / model.body_mass[POLE]
    return model.replace(
        dof_damping=model.dof_damping.at[0].set(params["damping"]),
        body_mass=model.body_mass.at[POLE].set(params["mass"]),
        body_inertia=model.body_inertia.at[POLE].mul(scale),
    )


def make_system(damping: Any, mass: Any, observe: str = "qpos") -> MJXSystem:
    """The MJX pendulum with the given physical parameters; state ``[θ, ω]``, input
    ``[torque]``, observation ``θ`` (``observe="qpos"``)."""
    dtype = jnp.result_type(float)
    params = {"damping": jnp.asarray(damping, dtype), "mass": jnp.asarray(mass, dtype)}
    return MJXSystem.from_xml(PENDULUM_XML, params=params, bind=bind, observe=observe)


class Data(NamedTuple):
    x0: jax.Array  # (B, 2) initial states
    us: jax.Array  # (B, N, 1) torques
    ys: jax.Array  # (B, N, 1) noisy angles of x_1 … x_N
    xs: jax.Array  # (B, N+1, 2) true states


def simulate(system: MJXSystem, key: jax.Array, batch: int = 4, steps: int = 150) -> Data:
    """Random torque sequences (smoothed white noise, ~1.5 N·m) from random initial angles,
    MJX rollouts of ``system`` and noisy angle measurements of every next state."""
    k0, ku, kn = jax.random.split(key, 3)
    dtype = jnp.result_type(float)
    x0 = jnp.stack([jax.random.uniform(k0, (batch,), dtype, -1.0, 1.0),
                    jnp.zeros(batch, dtype)], -1)
    white = jax.random.normal(ku, (batch, steps + 4, 1), dtype)
    us = 1.5 * (white[:, 4:] + white[:, 3:-1] + white[:, 2:-2] + white[:, 1:-3]) / 2.0
    xs, _ = jax.jit(jax.vmap(lambda x, u: rollout(system, x, u)))(x0, us)
    ys = xs[:, 1:, :1] + NOISE * jax.random.normal(kn, (batch, steps, 1), dtype)
    return Data(x0, us, ys, xs)


def predicted_measurement(
    filt: EKF | UKF, x: jax.Array, P: jax.Array, u: jax.Array, t: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Mean and covariance ``(ŷ, S)`` of the next measurement given the predicted state
    ``(x⁻, P⁻)``: ``h(x⁻)`` and ``H P⁻ Hᵀ + R`` (EKF, ``H = ∂h/∂x``), or the unscented
    transform of ``h`` (UKF sigma points, Merwe weights)."""
    h = lambda s: filt.model.observation(s, u, t)
    if isinstance(filt, EKF):
        H = jax.jacfwd(h)(x)
        return h(x), H @ P @ H.T + filt.R
    pts, _, wm, wc = filt.sigma_points(x, P)
    obs = jax.vmap(h)(pts)
    mean = wm @ obs
    dev = obs - mean
    return mean, (wc[:, None] * dev).T @ dev + filt.R


def filter_nll(
    system: MJXSystem, x0: jax.Array, us: jax.Array, ys: jax.Array, kind: str = "ekf"
) -> jax.Array:
    """Mean negative log-likelihood per measurement (constants dropped) of one sequence
    under a Kalman filter of ``system`` (``kind`` ``"ekf"`` or ``"ukf"``): predict with
    ``u_k``, score ``y_k`` against the predicted measurement, update with it."""
    Q, R = jnp.diag(jnp.array([1e-6, 1e-4])), jnp.eye(1) * NOISE**2
    filt = EKF(system, Q, R) if kind == "ekf" else UKF(system, Q, R)
    P0 = jnp.diag(jnp.array([1e-4, 1e-4]))

    def step(carry: tuple[jax.Array, jax.Array], inp: tuple[jax.Array, ...]):
        x, P = carry
        u, y, t = inp
        xp, Pp = filt.predict(x, P, u, t)
        yhat, S = predicted_measurement(filt, xp, Pp, u, t)
        L = jnp.linalg.cholesky(S)
        z = jax.scipy.linalg.solve_triangular(L, y - yhat, lower=True)
        nll = 0.5 * z @ z + jnp.sum(jnp.log(jnp.diag(L)))
        return filt.update(xp, Pp, y, u, t), nll

    ts = jnp.arange(us.shape[0])
    _, nll = jax.lax.scan(step, (x0, P0), (us, ys, ts))
    return jnp.mean(nll)


class History(NamedTuple):
    loss: jax.Array  # (steps,) mean NLL per measurement at each iteration
    damping: jax.Array  # (steps + 1,) estimates, initial guess first
    mass: jax.Array  # (steps + 1,)
    truth: dict[str, float]


def objective(data: Data, template: MJXSystem, kind: str = "ekf") -> Any:
    """``f(θ) → (NLL, ∂NLL/∂θ)`` over the batch, θ = log(damping, mass) (forward mode)."""

    def loss(theta: jax.Array) -> jax.Array:
        p = jnp.exp(theta)
        system = eqx.tree_at(lambda s: s.params, template, {"damping": p[0], "mass": p[1]})
        nll = jax.vmap(lambda x0, us, ys: filter_nll(system, x0, us, ys, kind))(
            data.x0, data.us, data.ys
        )
        return jnp.mean(nll)

    def value_and_grad(theta: jax.Array) -> tuple[jax.Array, jax.Array]:
        value, tangents = jax.vmap(
            lambda v: jax.jvp(loss, (theta,), (v,)), out_axes=(None, 0)
        )(jnp.eye(theta.shape[0], dtype=theta.dtype))
        return value, tangents

    return value_and_grad


def train(
    steps: int = 200,
    lr: float = 0.1,
    batch: int = 4,
    horizon: int = 150,
    seed: int = 0,
    kind: str = "ekf",
    truth: dict[str, float] | None = None,
    guess: dict[str, float] | None = None,
) -> History:
    """Fit log(damping, mass) to MJX rollouts of the true pendulum by Adam on the filter's
    likelihood (``kind`` ``"ekf"``/``"ukf"``); the whole loop (``steps`` iterations) is one
    jitted ``lax.scan``."""
    if kind not in ("ekf", "ukf"):
        raise ValueError(f"kind: expected 'ekf' or 'ukf', got {kind!r}")
    truth = dict(TRUE if truth is None else truth)
    guess = dict(GUESS if guess is None else guess)
    data = simulate(make_system(**truth), jax.random.PRNGKey(seed), batch, horizon)
    value_and_grad = objective(data, make_system(**guess), kind)
    opt = optax.adam(lr)
    theta0 = jnp.log(jnp.array([guess["damping"], guess["mass"]]))

    def step(carry: tuple[jax.Array, Any], _: Any):
        theta, state = carry
        loss, g = value_and_grad(theta)
        updates, state = opt.update(g, state, theta)
        theta = optax.apply_updates(theta, updates)
        return (theta, state), (loss, jnp.exp(theta))

    run = jax.jit(lambda th: jax.lax.scan(step, (th, opt.init(th)), None, length=steps))
    _, (loss, est) = run(theta0)
    est = jnp.concatenate([jnp.exp(theta0)[None], est])
    return History(loss, est[:, 0], est[:, 1], truth)


def format_table(hist: History, rows: int = 11) -> str:
    """The learning curve as a text table (``rows`` iterations, evenly spaced)."""
    n = int(hist.loss.shape[0])
    idx = sorted({int(round(i)) for i in np.linspace(0, n, rows)})
    lines = [
        f"{'iter':>5} {'NLL/meas':>10} {'damping':>9} {'mass':>8} {'|Δdamp|':>9} {'|Δmass|':>9}",
    ]
    for i in idx:
        loss = f"{float(hist.loss[i]):10.4f}" if i < n else f"{'—':>10}"
        d, m = float(hist.damping[i]), float(hist.mass[i])
        lines.append(
            f"{i:5d} {loss} {d:9.4f} {m:8.4f} {abs(d - hist.truth['damping']):9.2e} "
            f"{abs(m - hist.truth['mass']):9.2e}"
        )
    lines.append(f"truth {'':>10} {hist.truth['damping']:9.4f} {hist.truth['mass']:8.4f}")
    return "\n".join(lines)


def plot(hist: History, path: str | None = None) -> None:  # pragma: no cover - optional
    """Learning curve: NLL and the two parameter estimates against the truth."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(12, 3.2))
    ax[0].plot(hist.loss)
    ax[0].set(title="EKF negative log-likelihood / measurement", xlabel="iteration")
    for a, key in zip(ax[1:], ("damping", "mass")):
        a.plot(getattr(hist, key), label="estimate")
        a.axhline(hist.truth[key], color="k", ls="--", label="MJX truth")
        a.set(title=f"pole {key}", xlabel="iteration")
        a.legend()
    fig.tight_layout()
    if path:
        fig.savefig(path)


def main(argv: list[str] | None = None) -> History:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--horizon", type=int, default=150, help="measurements per sequence")
    ap.add_argument("--batch", type=int, default=4, help="sequences")
    ap.add_argument("--filter", choices=("ekf", "ukf"), default="ekf")
    ap.add_argument("--plot", type=str, default=None, help="save the learning curve here")
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    hist = train(steps=args.steps, batch=args.batch, horizon=args.horizon, kind=args.filter)
    dt = time.perf_counter() - t0
    print(f"{args.steps} Adam steps ({args.filter.upper()} likelihood) on {args.batch}×"
          f"{args.horizon} MJX measurements in {dt:.1f} s (compilation included)")
    print(format_table(hist))
    if args.plot:
        plot(hist, args.plot)
    return hist


if __name__ == "__main__":
    main()
