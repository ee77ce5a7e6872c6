"""MPC benchmark on the imitation-learning problem: jaxpose vs PyPose's ``pp.module.MPC``.

The problem (Amos et al. 2018; PyPose's ``examples/module/mpc/linear.py``): a learner
with linear dynamics (A, B) plans with MPC under the expert's quadratic cost (Q = I,
p ~ N(0, 1), horizon T, no terminal cost) from a batch of initial states; the loss is
``mean((u − u*)²) + mean((x − x*)²)`` against the expert's plan (precomputed). Timed:

* forward: MPC solve + loss (PyPose: with the autograd graph, as in training);
* backward: gradient of the loss w.r.t. (A, B) given the forward pass (PyPose:
  ``loss.backward()``; jaxpose: the VJP from ``jax.vjp``, i.e. the implicit-function
  backward — one extra LQR-structured solve);
* forward + backward together.

Sizes: state n ∈ {4, 16, 64} with m = n controls (as the seed problem), batch ∈ {1, 16,
64}, T = 5. jaxpose: ``jit``; compile time reported separately. PyPose runs on torch CPU
with ``stepper=ReduceToBason(steps=2)``: one no-grad LQR pass plus the final LQR pass
with gradients — the fewest PyPose's MPC can do (its default stepper stops after the
same single pass at batch 1, and raises "Boolean value of Tensor with more than one value
is ambiguous" at batch > 1). Both libraries solve the same problem; the planned controls
and the gradients are compared and the largest differences printed.

jaxpose's ``MPC`` recognises the linear–quadratic structure and solves it with one
Riccati pass (``solver="auto"``); ``--solvers auto,ilqr`` also times the generic iLQR path
on the same problem. Usage::

    python bench/control.py [--quick] [--dtype float32|float64] [--sizes 4,16,64]
                            [--batches 1,16,64] [--horizon 5] [--solvers auto] [--out F.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

if __package__ in (None, ""):  # run as a script: make `bench` and `jaxpose` importable
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bench._common import script_threads  # noqa: E402 - imports no jax

THREADS = script_threads(__name__)  # caps the BLAS/OpenMP pools before numpy/jax/torch load

import jax  # noqa: E402 - after the BLAS thread caps
import numpy as np  # noqa: E402

from bench._common import (  # noqa: E402
    Peer,
    Timing,
    apply_common,
    emit_report,
    environment,
    fmt_ratio,
    fmt_seconds,
    import_peer,
    markdown_table,
    parser,
    time_callable,
    time_jax,
    to_numpy,
    to_torch,
)

BAR = 5.0  # required jaxpose / PyPose speed ratio on every configuration (issue 5)


# ----------------------------------------------------------------------------------
# Problem
# ----------------------------------------------------------------------------------
def make_problem(n: int, batch: int, T: int, dtype: str, seed: int = 0) -> dict[str, Any]:
    """Expert (A*, B*, Q, p), learner (A, B) and initial states, as numpy arrays."""
    rng = np.random.default_rng(seed + 1000 * n + batch)
    m = n
    prob = {
        "A_star": np.eye(n) + 0.2 * rng.normal(size=(n, n)) / np.sqrt(n / 4),
        "B_star": rng.normal(size=(n, m)) / np.sqrt(n / 4),
        "A": np.eye(n) + 0.2 * rng.normal(size=(n, n)) / np.sqrt(n / 4),
        "B": rng.normal(size=(n, m)) / np.sqrt(n / 4),
        "Q": np.eye(n + m),
        "p": rng.normal(size=n + m),
        "x0": rng.normal(size=(batch, n)),
    }
    out = {k: v.astype(dtype) for k, v in prob.items()}
    out.update(n=n, m=m, T=T, batch=batch)
    return out


# ----------------------------------------------------------------------------------
# jaxpose
# ----------------------------------------------------------------------------------
@dataclass
class Result:
    fwd: Timing | None = None
    bwd: Timing | None = None
    both: Timing | None = None
    u: np.ndarray | None = None
    grad_A: np.ndarray | None = None
    error: str | None = None


def run_jaxpose(prob: dict[str, Any], solver: str, timing_kw: dict[str, Any]) -> Result:
    import jax.numpy as jnp

    from jaxpose.control import MPC, QuadraticCost
    from jaxpose.dynamics import LTI

    T = prob["T"]
    Q, p, x0 = (jnp.asarray(prob[k]) for k in ("Q", "p", "x0"))

    def plan(A: jax.Array, B: jax.Array) -> tuple[jax.Array, jax.Array]:
        sol = MPC(LTI(A, B), QuadraticCost(Q, p), T, solver=solver)(x0)
        return sol.x, sol.u

    x_true, u_true = jax.jit(plan)(jnp.asarray(prob["A_star"]), jnp.asarray(prob["B_star"]))

    def loss(A: jax.Array, B: jax.Array) -> jax.Array:
        x, u = plan(A, B)
        return jnp.mean((u - u_true) ** 2) + jnp.mean((x - x_true) ** 2)

    A, B = jnp.asarray(prob["A"]), jnp.asarray(prob["B"])
    res = Result()
    res.fwd, _ = time_jax(loss, A, B, **timing_kw)
    _, vjp_fn = jax.jit(lambda a, b: jax.vjp(loss, a, b))(A, B)
    one = jnp.ones((), A.dtype)
    res.bwd, _ = time_jax(lambda f: f(one), vjp_fn, **timing_kw)
    res.both, (_, grads) = time_jax(jax.value_and_grad(loss, argnums=(0, 1)), A, B, **timing_kw)
    res.u = np.asarray(jax.jit(plan)(A, B)[1])
    res.grad_A = np.asarray(grads[0])
    return res


# ----------------------------------------------------------------------------------
# PyPose
# ----------------------------------------------------------------------------------
def run_pypose(pp: Any, prob: dict[str, Any], timing_kw: dict[str, Any]) -> Result:
    import torch

    T, n, m, nb = prob["T"], prob["n"], prob["m"], prob["batch"]
    t = lambda k: to_torch(prob[k])
    dtype = t("Q").dtype
    Q = torch.tile(t("Q"), (nb, T, 1, 1))
    p = torch.tile(t("p"), (nb, T, 1))
    x0 = t("x0")
    C = torch.eye(n, dtype=dtype)
    D = torch.zeros(n, m, dtype=dtype)
    c1 = torch.zeros(n, dtype=dtype)
    c2 = torch.zeros(n, dtype=dtype)

    def mpc_for(A: Any, B: Any) -> Any:
        lti = pp.module.LTI(A, B, C, D, c1, c2)
        return pp.module.MPC(lti, Q, p, T, stepper=pp.utils.ReduceToBason(steps=2))

    with torch.no_grad():
        x_true, u_true, _ = mpc_for(t("A_star"), t("B_star"))(1, x0)
    A = t("A").clone().requires_grad_()
    B = t("B").clone().requires_grad_()
    mpc = mpc_for(A, B)

    def forward() -> Any:
        x, u, _ = mpc(1, x0)
        return torch.mean((u - u_true) ** 2) + torch.mean((x - x_true) ** 2)

    def both() -> Any:
        A.grad = None
        B.grad = None
        loss = forward()
        loss.backward()
        return loss

    res = Result()
    res.fwd, _ = time_callable(forward, **timing_kw)
    res.bwd = _time_backward(forward, A, B, timing_kw)
    res.both, _ = time_callable(both, **timing_kw)
    both()
    res.grad_A = to_numpy(A.grad).copy()
    with torch.no_grad():
        res.u = to_numpy(mpc(1, x0)[1])
    return res


def _time_backward(forward: Any, A: Any, B: Any, timing_kw: dict[str, Any]) -> Timing:
    """``loss.backward()`` alone: a fresh graph per sample, only the backward timed."""
    import statistics

    repeats = max(3, timing_kw.get("repeats", 7))
    max_time = timing_kw.get("max_time", 10.0)
    samples: list[float] = []
    spent = 0.0
    for _ in range(repeats + 1):
        A.grad = None
        B.grad = None
        loss = forward()
        t0 = time.perf_counter()
        loss.backward()
        dt = time.perf_counter() - t0
        samples.append(dt)
        spent += dt
        if spent > max_time and len(samples) >= 3:
            break
    samples = samples[1:]  # first backward warms up the autograd engine
    return Timing(min(samples), statistics.median(samples), len(samples), 1)


# ----------------------------------------------------------------------------------
# Driver and report
# ----------------------------------------------------------------------------------
@dataclass
class Config:
    dtype: str = "float32"
    sizes: tuple[int, ...] = (4, 16, 64)
    batches: tuple[int, ...] = (1, 16, 64)
    horizon: int = 5
    solvers: tuple[str, ...] = ("auto",)
    timing_kw: dict[str, Any] = field(default_factory=dict)


def run(cfg: Config, log: Any = None) -> tuple[list[dict[str, Any]], Peer]:
    peer = import_peer("pypose")
    if peer.available:
        import torch

        torch.set_default_dtype(getattr(torch, cfg.dtype))
    rows = []
    for n in cfg.sizes:
        for nb in cfg.batches:
            prob = make_problem(n, nb, cfg.horizon, cfg.dtype)
            cell: dict[str, Any] = {"n": n, "batch": nb}
            for solver in cfg.solvers:
                if log:
                    log(f"jaxpose[{solver}] n={n} batch={nb}")
                cell[f"jaxpose:{solver}"] = run_jaxpose(prob, solver, cfg.timing_kw)
            if peer.available:
                if log:
                    log(f"pypose n={n} batch={nb}")
                try:
                    cell["pypose"] = run_pypose(peer.module, prob, cfg.timing_kw)
                except Exception as err:  # noqa: BLE001 - reported, never faked
                    cell["pypose"] = Result(error=f"{type(err).__name__}: {err}")
            rows.append(cell)
    return rows, peer


def _best(t: Timing | None) -> float | None:
    return None if t is None else t.best


def report(rows: list[dict[str, Any]], peer: Peer, cfg: Config) -> str:
    lines = [
        f"# MPC imitation benchmark (T = {cfg.horizon}, m = n, {cfg.dtype})",
        "",
        f"Machine: {environment()}. Peer: {peer.label()}. Threads per library: "
        f"{THREADS if THREADS > 0 else 'library default'}.",
        "Times are the best of repeated steady-state runs; compile times separate. "
        "Ratios are PyPose time / jaxpose time (higher = jaxpose faster); bar ≥ "
        f"{BAR:.0f}x.",
        "",
    ]
    for solver in cfg.solvers:
        key = f"jaxpose:{solver}"
        header = [
            "n",
            "batch",
            "fwd jaxpose",
            "fwd PyPose",
            "fwd ratio",
            "bwd jaxpose",
            "bwd PyPose",
            "bwd ratio",
            "fwd+bwd jaxpose",
            "fwd+bwd PyPose",
            "fwd+bwd ratio",
            "compile fwd / fwd+bwd",
            "max |Δu|",
            "max rel |ΔdA|",
        ]
        table = []
        worst: float | None = None
        for cell in rows:
            jr: Result = cell[key]
            pr: Result | None = cell.get("pypose")
            ok_peer = pr is not None and pr.error is None
            ratios = []
            row = [cell["n"], cell["batch"]]
            for attr in ("fwd", "bwd", "both"):
                tj = _best(getattr(jr, attr))
                tp = _best(getattr(pr, attr)) if ok_peer else None
                row += [
                    fmt_seconds_fine(tj),
                    fmt_seconds_fine(tp) if ok_peer else "skipped",
                    fmt_ratio(tp, tj) if ok_peer else "skipped",
                ]
                if ok_peer and tj and tp:
                    ratios.append(tp / tj)
            comp = f"{fmt_seconds(jr.fwd.compile_s)} / {fmt_seconds(jr.both.compile_s)}"
            row.append(comp)
            if ok_peer:
                du = float(np.max(np.abs(jr.u - pr.u)))
                scale = max(1e-12, float(np.max(np.abs(pr.grad_A))))
                dA = float(np.max(np.abs(jr.grad_A - pr.grad_A))) / scale
                row += [f"{du:.1e}", f"{dA:.1e}"]
            else:
                row += ["—", "—"]
            if ratios:
                worst = min(ratios) if worst is None else min(worst, *ratios)
            table.append(row)
        lines.append(f"## jaxpose MPC solver = {solver!r}")
        lines.append("")
        lines.append(markdown_table(header, table))
        lines.append("")
        errors = [
            f"n={c['n']} batch={c['batch']}: {c['pypose'].error}"
            for c in rows
            if c.get("pypose") is not None and c["pypose"].error
        ]
        if errors:
            lines.append("PyPose failed (reported, not timed): " + "; ".join(errors))
        if worst is not None:
            verdict = "meets" if worst >= BAR else "misses"
            lines.append(f"Result: smallest ratio {worst:.1f}x — {verdict} the {BAR:.0f}x bar.")
        elif not peer.available:
            lines.append("PyPose skipped: no ratios.")
        lines.append("")
    return "\n".join(lines)


def fmt_seconds_fine(s: float | None) -> str:
    if s is None:
        return "—"
    if s < 1e-3:
        return f"{s * 1e6:.0f} µs"
    return fmt_seconds(s) if s >= 0.01 else f"{s * 1e3:.1f} ms"



def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = parser(__doc__, quick="fewer repeats (smoke run)")
    ap.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    ap.add_argument("--sizes", default="4,16,64")
    ap.add_argument("--batches", default="1,16,64")
    ap.add_argument("--horizon", type=int, default=5)
    ap.add_argument("--solvers", default="auto", help="comma list of auto, lqr, ilqr")
    ap.add_argument("-v", "--verbose", action="store_true")
    return ap.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> str:
    args = parse_args(argv)
    apply_common(args)
    global THREADS
    THREADS = args.threads
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    timing_kw = (
        {"repeats": 3, "min_time": 0.01, "max_time": 1.0}
        if args.quick
        else {"repeats": 7, "min_time": 0.05, "max_time": 5.0}
    )
    cfg = Config(
        args.dtype,
        tuple(int(s) for s in args.sizes.split(",") if s),
        tuple(int(b) for b in args.batches.split(",") if b),
        args.horizon,
        tuple(s for s in args.solvers.split(",") if s),
        timing_kw,
    )
    log = (lambda s: print(s, file=sys.stderr, flush=True)) if args.verbose else None
    rows, peer = run(cfg, log)
    text = report(rows, peer, cfg)
    return emit_report(text, args.out)


if __name__ == "__main__":
    main()
