"""Learned IMU calibration through the differentiable preintegrator (PyPose's IMU example).

A simulated IMU has a known error model: per-axis scale factors and misalignment
(``M_g``, ``M_a``), constant biases, gyroscope g-sensitivity (a rate error proportional
to the specific force) and white noise::

    gyro = M_g·ω + b_g + G·f + n_g,        acc = M_a·f + b_a + n_a.

A small equinox network (a linear layer plus an MLP, per sample, from the raw gyroscope
and accelerometer readings) outputs corrections of both signals. It is trained with optax
by supervising the *integrated* pose: each 1-s window of corrected samples is
preintegrated (:func:`jaxpose.imu.preintegrate`, values only) and propagated from the
ground-truth state at its start (:func:`jaxpose.imu.predict`); the loss is the squared
rotation error ``|Log(R_gtᵀR)|²`` plus the squared position error at the window's end,
differentiated through the preintegrator. Evaluated on held-out trajectories against raw
preintegration and the oracle (the true error model inverted, leaving only the noise):
the mean rotation and position errors of integrated windows, as in the EuRoC table of the
PyPose paper.

Run ``python notebooks/_examples/imu_calibration.py [--steps 1500] [--smoke]``.
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

from jaxpose.imu import NavState, dead_reckon, predict, preintegrate
from jaxpose.lie import SO3

GRAVITY = (0.0, 0.0, -9.81)
DT = 0.005  # 200 Hz


class SensorModel(NamedTuple):
    """The IMU's (unknown to the learner) error model; see the module docstring."""

    gyro_matrix: jax.Array  # M_g (3, 3)
    gyro_bias: jax.Array
    g_sensitivity: jax.Array  # G (3, 3) [rad/s per m/s²]
    acc_matrix: jax.Array  # M_a (3, 3)
    acc_bias: jax.Array
    gyro_sigma: float  # per-sample standard deviations
    acc_sigma: float

    def apply(self, key: jax.Array, gyro: jax.Array, acc: jax.Array) -> tuple[jax.Array, ...]:
        kg, ka = jax.random.split(key)
        g = (gyro @ self.gyro_matrix.T + self.gyro_bias + acc @ self.g_sensitivity.T
             + self.gyro_sigma * jax.random.normal(kg, gyro.shape, gyro.dtype))
        a = (acc @ self.acc_matrix.T + self.acc_bias
             + self.acc_sigma * jax.random.normal(ka, acc.shape, acc.dtype))
        return g, a

    def invert(self, gyro: jax.Array, acc: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The oracle correction: the error model inverted (noise stays)."""
        f = (acc - self.acc_bias) @ jnp.linalg.inv(self.acc_matrix).T
        w = (gyro - self.gyro_bias - f @ self.g_sensitivity.T) @ jnp.linalg.inv(
            self.gyro_matrix).T
        return w, f


def default_sensor(dtype: Any = None) -> SensorModel:
    """Errors of a consumer-grade MEMS IMU (scale ±2 %, misalignment ~0.5°, biases
    0.5–1°/s and 0.1–0.2 m/s², g-sensitivity ~0.1°/s per g)."""
    dtype = dtype or jnp.result_type(float)
    a = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    return SensorModel(
        gyro_matrix=a([[1.02, 0.008, -0.005], [-0.006, 0.985, 0.01], [0.004, -0.007, 1.015]]),
        gyro_bias=a([0.012, -0.008, 0.015]),
        g_sensitivity=a([[2e-4, -1e-4, 1.5e-4], [1e-4, 2.5e-4, -1e-4], [-1.5e-4, 1e-4, 2e-4]]),
        acc_matrix=a([[0.985, 0.006, -0.004], [-0.005, 1.02, 0.007], [0.006, -0.008, 1.01]]),
        acc_bias=a([0.15, -0.1, 0.2]),
        gyro_sigma=0.002,
        acc_sigma=0.02,
    )


class Trajectories(NamedTuple):
    gyro: jax.Array  # (S, N, 3) measured (raw)
    acc: jax.Array
    gyro_true: jax.Array
    acc_true: jax.Array
    states: NavState  # (S, N + 1): ground truth before/after every sample


def _smooth(key: jax.Array, shape: tuple[int, ...], t: jax.Array, amp: float,
            max_freq: float, dtype: Any) -> jax.Array:
    """Random sums of 4 sinusoids per axis: (S, N, 3)."""
    k1, k2, k3 = jax.random.split(key, 3)
    s = shape[0]
    freq = jax.random.uniform(k1, (s, 1, 3, 4), dtype, 0.05, max_freq)
    phase = jax.random.uniform(k2, (s, 1, 3, 4), dtype, 0.0, 2 * jnp.pi)
    a = amp * jax.random.normal(k3, (s, 1, 3, 4), dtype) / 2.0
    return jnp.sum(a * jnp.sin(2 * jnp.pi * freq * t[None, :, None, None] + phase), -1)


def simulate(key: jax.Array, sensor: SensorModel, num_seq: int, num_samples: int,
             dtype: Any = None) -> Trajectories:
    """Random smooth motions (angular rates ~1 rad/s, accelerations ~1 m/s²) under
    gravity; true specific forces are consistent with the integrator's zero-order hold,
    so integrating the true signals reproduces the ground truth to rounding."""
    dtype = dtype or jnp.result_type(float)
    kw, ka, kr, kn = jax.random.split(key, 4)
    t = jnp.arange(num_samples, dtype=dtype) * DT
    omega = _smooth(kw, (num_seq,), t, 1.0, 0.5, dtype)
    a_nav = _smooth(ka, (num_seq,), t, 1.0, 0.3, dtype)
    rot0 = SO3.random(kr, (num_seq,), dtype=dtype)
    zeros = jnp.zeros((num_seq, num_samples, 3), dtype)
    # rotations before each sample (dead reckoning of the rates alone)
    rots = dead_reckon(omega, zeros, DT, jnp.zeros(3, dtype),
                       NavState(rot0, jnp.zeros((num_seq, 3), dtype),
                                jnp.zeros((num_seq, 3), dtype))).rot.data
    before = jnp.concatenate([rot0.data[:, None], rots[:, :-1]], 1)
    g = jnp.asarray(GRAVITY, dtype)
    f_true = SO3(before).inv().act(a_nav - g)  # Rᵀ(a − g)
    init = NavState(rot0, jnp.zeros((num_seq, 3), dtype), jnp.zeros((num_seq, 3), dtype))
    after = dead_reckon(omega, f_true, DT, g, init)
    states = jax.tree.map(lambda i, s: jnp.concatenate([i[:, None], s], 1), init, after)
    gyro, acc = sensor.apply(kn, omega, f_true)
    return Trajectories(gyro, acc, omega, f_true, states)


class Windows(NamedTuple):
    gyro: jax.Array  # (W, L, 3)
    acc: jax.Array
    gyro_true: jax.Array
    acc_true: jax.Array
    start: NavState  # (W,)
    end: NavState  # (W,)


def windows(tr: Trajectories, length: int, stride: int) -> Windows:
    """Every window of ``length`` samples starting each ``stride`` samples."""
    n = tr.gyro.shape[1]
    starts = np.arange(0, n - length + 1, stride)
    idx = starts[:, None] + np.arange(length)[None]
    cut = lambda x: x[:, idx].reshape(-1, length, 3)  # noqa: E731
    at = lambda k: jax.tree.map(lambda x: x[:, k].reshape(-1, *x.shape[2:]), tr.states)  # noqa: E731
    return Windows(cut(tr.gyro), cut(tr.acc), cut(tr.gyro_true), cut(tr.acc_true),
                   at(starts), at(starts + length))


class Corrector(eqx.Module):
    """Per-sample correction of raw (gyro, acc): a linear layer plus a small MLP on the
    normalised readings; outputs are added to the readings (zero-initialised output
    layers, so training starts from raw preintegration)."""

    linear: eqx.nn.Linear
    mlp: eqx.nn.MLP
    scale: tuple[float, ...] = eqx.field(static=True)

    def __init__(self, key: jax.Array, width: int = 64, depth: int = 2, dtype: Any = None):
        dtype = dtype or jnp.result_type(float)
        k1, k2 = jax.random.split(key)
        lin = eqx.nn.Linear(6, 6, key=k1, dtype=dtype)
        mlp = eqx.nn.MLP(6, 6, width, depth, activation=jax.nn.tanh, key=k2, dtype=dtype)
        zero = lambda m: eqx.tree_at(lambda x: (x.weight, x.bias), m,  # noqa: E731
                                     (jnp.zeros_like(m.weight), jnp.zeros_like(m.bias)))
        self.linear = zero(lin)
        self.mlp = eqx.tree_at(lambda m: m.layers[-1], mlp, zero(mlp.layers[-1]))
        self.scale = (0.05,) * 3 + (0.5,) * 3  # typical correction sizes

    def __call__(self, gyro: jax.Array, acc: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = jnp.concatenate([gyro, acc / 9.81], -1)
        flat = x.reshape(-1, 6)
        out = jax.vmap(lambda v: self.linear(v) + self.mlp(v))(flat).reshape(x.shape)
        out = out * jnp.asarray(self.scale, x.dtype)
        return gyro + out[..., :3], acc + out[..., 3:]


def window_errors(gyro: jax.Array, acc: jax.Array, w: Windows) -> tuple[jax.Array, jax.Array]:
    """Rotation error |Log(R_gtᵀR)| [rad] and position error [m] (W,) of integrating each
    window from its true start state."""
    pre = preintegrate(gyro, acc, DT, bias_jacobians=False, check=False)
    end = predict(w.start, pre, jnp.asarray(GRAVITY, gyro.dtype))
    rot = (w.end.rot.inv() @ end.rot).log().data
    return jnp.linalg.norm(rot, axis=-1), jnp.linalg.norm(end.pos - w.end.pos, axis=-1)


_window_errors = jax.jit(window_errors)


def loss_fn(model: Corrector, w: Windows, pos_weight: float = 10.0) -> jax.Array:
    g, a = model(w.gyro, w.acc)
    pre = preintegrate(g, a, DT, bias_jacobians=False, check=False)
    end = predict(w.start, pre, jnp.asarray(GRAVITY, g.dtype))
    rot = (w.end.rot.inv() @ end.rot).log().data
    return jnp.mean(jnp.sum(rot**2, -1) + pos_weight * jnp.sum((end.pos - w.end.pos) ** 2, -1))


class History(NamedTuple):
    loss: jax.Array  # (steps,)
    model: Corrector
    table: dict[str, tuple[float, float]]  # method → (rotation error [deg], position [m])
    seconds: float
    test: Windows  # the held-out windows


def train(steps: int = 1500, num_train: int = 32, num_test: int = 8,
          num_samples: int = 4000, window: int = 200, batch: int = 64, lr: float = 3e-3,
          seed: int = 0, dtype: Any = None) -> History:
    """Simulate, train the corrector with Adam, evaluate on held-out trajectories."""
    dtype = dtype or jnp.result_type(float)
    sensor = default_sensor(dtype)
    k_train, k_test, k_model, k_batch = jax.random.split(jax.random.PRNGKey(seed), 4)
    train_w = windows(simulate(k_train, sensor, num_train, num_samples, dtype), window,
                      window // 4)
    test_w = windows(simulate(k_test, sensor, num_test, num_samples, dtype), window, window)
    model = Corrector(k_model, dtype=dtype)
    params, static = eqx.partition(model, eqx.is_array)
    opt = optax.adam(optax.cosine_decay_schedule(lr, steps, alpha=0.05))
    n_win = train_w.gyro.shape[0]

    def step(carry: Any, k: jax.Array, data: Windows) -> tuple[Any, jax.Array]:
        p, s = carry
        b = jax.tree.map(lambda x: x[jax.random.choice(k, n_win, (batch,), replace=False)],
                         data)
        loss, grads = jax.value_and_grad(lambda p: loss_fn(eqx.combine(p, static), b))(p)
        updates, s = opt.update(grads, s, p)
        return (optax.apply_updates(p, updates), s), loss

    @jax.jit
    def run(p: Any, key: jax.Array, data: Windows) -> tuple[Any, jax.Array]:
        (p, _), losses = jax.lax.scan(lambda c, k: step(c, k, data), (p, opt.init(p)),
                                      jax.random.split(key, steps))
        return p, losses

    t0 = time.perf_counter()
    params, losses = run(params, k_batch, train_w)
    jax.block_until_ready(losses)
    seconds = time.perf_counter() - t0
    model = eqx.combine(params, static)
    table = evaluate(model, sensor, test_w)
    return History(losses, model, table, seconds, test_w)


def evaluate(model: Corrector, sensor: SensorModel, w: Windows) -> dict[str, tuple[float, float]]:
    """Mean rotation [deg] and position [m] errors of integrated test windows."""
    out = {}
    signals = {
        "raw preintegration": (w.gyro, w.acc),
        "learned correction": model(w.gyro, w.acc),
        "oracle (true model inverted)": sensor.invert(w.gyro, w.acc),
    }
    for name, (g, a) in signals.items():
        rot, pos = _window_errors(g, a, w)
        out[name] = (float(jnp.degrees(jnp.mean(rot))), float(jnp.mean(pos)))
    return out


def format_table(table: dict[str, tuple[float, float]], window_s: float) -> str:
    raw = table["raw preintegration"]
    lines = [f"| method ({window_s:g}-s windows) | rotation error [deg] | position error [m] |"
             " rotation / raw | position / raw |",
             "|---|---:|---:|---:|---:|"]
    for name, (r, p) in table.items():
        lines.append(f"| {name} | {r:.4f} | {p:.4f} | {r / raw[0]:.3f} | {p / raw[1]:.3f} |")
    return "\n".join(lines)


def plot(hist: History, path: str | None = None) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.semilogy(np.asarray(hist.loss))
    ax.set_xlabel("Adam step")
    ax.set_ylabel("training loss")
    ax.set_title("IMU calibration through the preintegrator")
    fig.tight_layout()
    if path:
        fig.savefig(path, dpi=120)
    else:
        plt.show()


def main(argv: list[str] | None = None) -> History:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--smoke", action="store_true", help="tiny sizes (seconds)")
    ap.add_argument("--plot", type=str, default=None, help="save the loss curve here")
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    kw: dict[str, Any] = {"steps": args.steps}
    if args.smoke:
        kw = {"steps": min(args.steps, 150), "num_train": 4, "num_test": 2,
              "num_samples": 1000, "batch": 16}
    hist = train(**kw)
    loss = np.asarray(hist.loss)
    print(f"trained {loss.size} Adam steps in {hist.seconds:.1f} s (incl. compile); "
          f"loss {loss[:10].mean():.3e} -> {loss[-10:].mean():.3e}")
    print(format_table(hist.table, 200 * DT))
    if args.plot:
        plot(hist, args.plot)
    return hist


if __name__ == "__main__":
    main()
