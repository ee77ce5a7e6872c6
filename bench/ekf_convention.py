"""EKF measurement convention: jaxpose's standard EKF vs PyPose's ``EKF.forward`` on
PyPose's own docstring example (an accuracy comparison, not a timing).

PyPose's ``ekf(x, y, u, P)`` predicts ``x⁻ = f(x)`` but forms the innovation with the
observation model linearised and evaluated at the *previous* state, ``y − h(x)``, and
applies it to ``x⁻``; its docstring example generates ``y_i = h(x_i, u_i)``, a measurement
of the state before the step. jaxpose's ``EKF.step`` is the textbook EKF: predict, then
correct with ``y`` as a measurement of the *predicted* state ``h(x⁻)``. For data of
PyPose's kind, jaxpose's ``update`` (with ``y_i`` at ``x_i``) followed by ``predict`` is
the matching standard filter.

System (PyPose's example): ``x⁺ = cos x + u``, ``y = sin x + u``, N = 2, q = r = 0.1,
p = 10, float64. For each seed the same noisy data go to every filter; the table gives
the final-state error ‖x_T − x̂_T‖ over ``--seeds`` seeds, for data generated both ways.

Usage::

    python bench/ekf_convention.py [--quick] [--seeds 100] [--steps 5,20] [--out F.md]
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

if __package__ in (None, ""):  # run as a script: make `bench` and `jaxpose` importable
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench._common import emit_report, import_peer, markdown_table, parser  # noqa: E402
from jaxpose.dynamics import NLS  # noqa: E402
from jaxpose.filters import EKF  # noqa: E402

N, Q_STD, R_STD, P_STD = 2, 0.1, 0.1, 10.0


class _Example(NLS):
    def state_transition(self, x, u, t=0):
        return jnp.cos(x) + u

    def observation(self, x, u, t=0):
        return jnp.sin(x) + u


def _filters() -> tuple[EKF, object, object]:
    ekf = EKF(_Example(), np.eye(N) * Q_STD**2, np.eye(N) * R_STD**2)
    run = eqx.filter_jit(ekf.run)

    @eqx.filter_jit
    def update_then_predict(x, P, ys, us):
        def body(carry, yu):
            x, P = ekf.update(*carry, *yu)
            return ekf.predict(x, P, yu[1]), None

        return jax.lax.scan(body, (x, P), (ys, us))[0][0]

    return ekf, run, update_then_predict


def _one(pp, torch, seed: int, steps: int, new_state: bool, run, utp) -> tuple[float, ...]:
    torch.manual_seed(seed)

    class Example(pp.module.NLS):
        def state_transition(self, state, input, t=None):
            return state.cos() + input

        def observation(self, state, input, t=None):
            return state.sin() + input

    f64 = torch.float64
    model = Example()
    ekf = pp.module.EKF(model).double()
    states = torch.zeros(steps, N, dtype=f64)
    inputs = torch.randn(steps, N, dtype=f64)
    Q, R = torch.eye(N, dtype=f64) * Q_STD**2, torch.eye(N, dtype=f64) * R_STD**2
    P = torch.eye(N, dtype=f64) * P_STD**2
    x = torch.randn(N, dtype=f64) * P_STD
    x0, ys = x.clone(), []
    for i in range(steps - 1):
        w = Q_STD * torch.randn(N, dtype=f64)
        v = R_STD * torch.randn(N, dtype=f64)
        states[i + 1], y = model(states[i] + w, inputs[i])
        if new_state:  # y_i measures x_{i+1} (jaxpose's convention)
            y = model.observation(states[i + 1], inputs[i])
        ys.append((y + v).numpy())
        with torch.no_grad():
            x, P = ekf(x, y + v, inputs[i], P, Q, R)
    truth = states[-1].numpy()
    P0 = np.eye(N) * P_STD**2
    us = inputs[:-1].numpy()
    ours = np.asarray(run(jnp.asarray(x0.numpy()), P0, np.stack(ys), us).x[-1])
    swapped = np.asarray(utp(jnp.asarray(x0.numpy()), jnp.asarray(P0), np.stack(ys), us))
    return tuple(float(np.linalg.norm(truth - e)) for e in (x.numpy(), ours, swapped))


def main(argv: Sequence[str] | None = None) -> str:
    """Run, print and return the report."""
    ap = parser(__doc__, quick="20 seeds", threads=False)
    ap.add_argument("--seeds", type=int, default=None)
    ap.add_argument("--steps", default="5,20", help="comma-separated sequence lengths T")
    args = ap.parse_args(argv)
    seeds = args.seeds or (20 if args.quick else 100)
    jax.config.update("jax_enable_x64", True)
    peer = import_peer("pypose")
    lines = ["# EKF measurement convention (accuracy, float64)", "",
             f"PyPose: {peer.label()}; {seeds} seeds per row; final-state error ‖x_T − x̂_T‖."]
    if not peer.available:
        return emit_report("\n".join(lines + ["", "Result: skipped (PyPose not installed)"]),
                           args.out)
    import torch

    _, run, utp = _filters()
    rows, ok = [], True
    for new_state in (False, True):
        for steps in (int(s) for s in args.steps.split(",")):
            errs = np.array([_one(peer.module, torch, s, steps, new_state, run, utp)
                             for s in range(seeds)])
            data = "y_i = h(x_{i+1}) (jaxpose)" if new_state else "y_i = h(x_i) (PyPose)"
            med, mean = np.median(errs, 0), errs.mean(0)
            rows.append([data, steps, *(f"{m:.3f} / {a:.3f}" for m, a in zip(med, mean))])
            matched = mean[1] if new_state else mean[2]
            ok &= bool(matched <= mean[0])
    lines += ["", markdown_table(
        ["data", "T", "PyPose ekf(x, y) median / mean", "jaxpose step median / mean",
         "jaxpose update→predict median / mean"], rows)]
    lines += ["", "Result: the jaxpose filter matching the data's convention is "
              f"{'at least as accurate as' if ok else 'NOT as accurate as'} PyPose's on "
              "every row"]
    return emit_report("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
