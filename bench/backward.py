"""Cost of the backward pass through ``graph.solve`` against one forward LM iteration.

For each problem (parking-garage and sphere2500 pose graphs, the largest BAL problem in
``../shared/data/bal`` — a few dozen observations — and a synthetic BAL problem of
realistic size, ``synthetic_bal(20, 2000)``: 20 cameras, 2 000 points, 10 000
observations; both with cameras 0 and 1 fixed, BA's gauge) a loss
``L(θ) = Σ w ⊙ X*(θ) + cost`` of the solution ``X*`` is differentiated with respect to a
perturbation θ of every measurement (pose graphs: ``Z ⊕ θ``; BAL: observations + θ).
Each contestant runs in its own cold process:

* ``forward``: ``jit(L)`` — one LM solve (its iteration count k gives the time of one
  iteration, forward / k);
* ``grad``: ``jit(grad(L))`` — the same solve plus the backward pass (exact Hessian at
  the solution, one solve by the forward's linear solver, the cross-derivative product).

Every solve uses ``graph.solve``'s default linear solver (``auto``: CHOLMOD for the pose
graphs, Schur elimination of the points for BA — what a user gets; the table names it) or
the one ``--solver`` names.

Backward = the median of grad − forward over alternating pairs of runs in the grad process
(the difference of the two processes' medians drifted by more than the backward itself);
unresolved when below its interquartile range or 5 % of the forward. Memory: the compiled
program's XLA buffers (arguments, outputs and temporaries from ``memory_analysis()``;
CHOLMOD's factor lives in the host callback and is not counted), grad against forward; the
process's peak resident set (``ru_maxrss``) is shown too but is dominated by compilation,
which is larger for the grad program. Compile time is reported next to each. The issue's
bar: backward ≤ one forward iteration, peak memory ≤ 1.5× the forward's (XLA buffers).

Usage::

    python bench/backward.py [--only garage,sphere2500,bal,bal-synthetic] [--quick]
                             [--solver auto|sparse|schur|pcg|dense]
                             [--dtype float64|float32] [--out F.md]

``--dtype float32`` runs everything in float32 (x64 off: the data, the solve and the
derivatives; CHOLMOD still factorises in float64 on the host).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # run as a script: make `bench` and `jaxpose` importable
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bench._common import (  # noqa: E402 - imports no jax
    ROOT,
    emit_report,
    environment,
    fmt_seconds,
    markdown_table,
    parser,
    spawn_worker,
    time_callable,
    worker_result,
)

NOISE = 0.05  # run-to-run spread of a median time, as a fraction of it
REPEATS = 11  # timed runs per contestant (3 gave medians 2x apart between runs on garage)
DATA = ROOT.parent / "shared" / "data"
PROBLEMS = ("garage", "sphere2500", "bal", "bal-synthetic")
SYNTHETIC_BAL = (20, 2000)  # cameras, points (5 observations per point)
QUICK = ("garage",)


def _bal_file() -> Path | None:
    files = sorted((DATA / "bal").glob("*.txt"), key=lambda p: p.stat().st_size)
    return files[-1] if files else None


def _source(name: str) -> Path | str | None:
    if name == "bal":
        return _bal_file()
    if name == "bal-synthetic":
        return "synthetic_bal({}, {})".format(*SYNTHETIC_BAL)
    path = DATA / "g2o" / ("parking-garage.g2o" if name == "garage" else f"{name}.g2o")
    return path if path.exists() else None


def _problem(name: str, solver: str) -> tuple[Any, Any, str]:
    """(loss(θ) -> (scalar, iterations), θ0, resolved linear solver) for problem ``name``
    solved with ``linear_solver=solver``."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxpose import graph as jg
    from jaxpose.datasets import synthetic_bal
    from jaxpose.io import read_bal, read_g2o
    from jaxpose.lie import LieGroup

    path = _source(name)
    if name == "bal-synthetic":
        # two cameras fixed: BA's gauge (a similarity) leaves the derivative undefined
        graph = jg.bundle_adjustment_problem(synthetic_bal(*SYNTHETIC_BAL, seed=0)[0],
                                             fixed_cameras=[0, 1])
    elif name == "bal":
        graph = jg.bundle_adjustment_problem(read_bal(path), fixed_cameras=[0, 1])
    else:
        graph = jg.pose_graph_problem(read_g2o(path))
    data = graph.factors[0].data
    theta0 = jnp.zeros((graph.factors[0].count, data.tangent_dim if isinstance(data, LieGroup)
                        else data.shape[-1]))
    leaves = jax.tree.leaves(graph.variables)
    rng = np.random.default_rng(0)
    weights = [jnp.asarray(rng.normal(size=x.shape)) for x in leaves]

    def loss(theta: Any) -> Any:
        new = data.retract(theta) if isinstance(data, LieGroup) else data + theta
        sol = jg.solve(eqx.tree_at(lambda g: g.factors[0].data, graph, new),
                       linear_solver=solver)
        value = sum(jnp.sum(w * x) for w, x in zip(weights, jax.tree.leaves(sol.variables),
                                                   strict=True))
        return value + sol.cost, sol.iterations

    return loss, theta0, jg.GraphLinearSolver(solver).resolve(graph)


def worker(name: str, mode: str, solver: str, dtype: str = "float64") -> None:
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", dtype == "float64")
    loss, theta0, method = _problem(name, solver)
    f = loss if mode == "forward" else jax.grad(loss, has_aux=True)
    t0 = time.perf_counter()
    compiled = jax.jit(f).lower(theta0).compile()  # kept: its memory_analysis() below
    compile_s = time.perf_counter() - t0
    timing, out = time_callable(lambda: compiled(theta0), repeats=REPEATS,
                                sync=jax.block_until_ready)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    mem = compiled.memory_analysis()
    xla_mb = (mem.temp_size_in_bytes + mem.argument_size_in_bytes + mem.output_size_in_bytes
              ) / 2**20 if mem is not None else float("nan")
    result = {"compile_s": compile_s, "run_s": timing.median, "iterations": int(out[1]),
              "peak_mb": peak_mb, "xla_mb": xla_mb, "method": method}
    if mode == "grad":
        # the backward's time: grad − forward in alternating pairs in this process (the
        # difference of two processes' medians drifted by more than the backward itself)
        forward = jax.jit(loss).lower(theta0).compile()
        pairs = []
        for _ in range(REPEATS):
            times = []
            for fn in (compiled, forward):
                t = time.perf_counter()
                jax.block_until_ready(fn(theta0))
                times.append(time.perf_counter() - t)
            pairs.append(times)
        g, fw = np.asarray(pairs).T
        result.update(backward_s=float(np.median(g - fw)),
                      backward_spread_s=float(np.subtract(*np.percentile(g - fw, [75, 25]))))
    worker_result(result)


def main(argv: Sequence[str] | None = None) -> int:
    ap = parser(__doc__, quick="parking-garage only", threads=False, workers=True)
    ap.add_argument("--only", default=None, help=f"comma-separated of {','.join(PROBLEMS)}")
    ap.add_argument("--solver", default="auto",
                    choices=("auto", "sparse", "schur", "pcg", "dense"),
                    help="graph.solve's linear_solver for every problem (default: auto; "
                    "schur needs a BA problem)")
    ap.add_argument("--dtype", default="float64", choices=("float64", "float32"))
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # NAME:MODE:SOLVER:DTYPE
    args = ap.parse_args(argv)
    if args.worker:
        worker(*args.worker.split(":"))
        return 0
    names = args.only.split(",") if args.only else list(QUICK if args.quick else PROBLEMS)
    rows, verdicts = [], []
    for name in names:
        src = _source(name)
        if src is None:
            rows.append([name] + ["—"] * 9 + ["skipped: data missing"])
            continue
        res = {}
        for mode in ("forward", "grad"):
            spec = f"{name}:{mode}:{args.solver}:{args.dtype}"
            res[mode] = spawn_worker([__file__, "--worker", spec], timeout=args.timeout)
        fw, gr = res["forward"], res["grad"]
        if "failed" in fw or "failed" in gr:
            why = fw.get("failed") or gr.get("failed")
            rows.append([name] + ["—"] * 9 + [f"failed: {why}"])
            verdicts.append(False)
            continue
        per_iter = fw["run_s"] / max(fw["iterations"], 1)
        backward = gr["backward_s"]
        # a difference within its interquartile spread (or NOISE of the forward) is not
        # resolved by the paired medians
        noise = max(NOISE * fw["run_s"], gr["backward_spread_s"])
        resolved = backward > noise
        mem = gr["xla_mb"] / fw["xla_mb"]
        ok = (backward <= per_iter or not resolved) and mem <= 1.5
        verdicts.append(ok)
        rows.append([
            f"{name} ({getattr(src, 'name', src)})", fw["method"], f"{fw['iterations']}",
            fmt_seconds(fw["run_s"]),
            fmt_seconds(per_iter),
            fmt_seconds(backward) if resolved else f"< {fmt_seconds(noise)} (noise)",
            f"{backward / per_iter:.2f}" if resolved else "—",
            f"{fw['xla_mb']:.1f} / {gr['xla_mb']:.1f} MB ({mem:.2f}x)",
            f"{fw['peak_mb']:.0f} / {gr['peak_mb']:.0f} MB",
            f"{fmt_seconds(fw['compile_s'])} / {fmt_seconds(gr['compile_s'])}",
            "yes" if ok else "no",
        ])
        print(" | ".join(rows[-1]), flush=True)  # kept if a later problem is cut off
    header = ["problem", "linear solver", "LM iterations", "forward", "per iteration", "backward",
              "backward / iteration", "XLA buffers forward / grad", "peak RSS forward / grad",
              "compile forward / grad",
              "bar met"]
    text = "\n".join([
        f"## Backward pass through graph.solve vs one forward LM iteration ({args.dtype})",
        "",
        f"{environment()}. linear_solver={args.solver!r} (resolved per problem in the "
        "table); steady state, median of the repeats; each contestant in a cold process.",
        "",
        markdown_table(header, rows),
        "",
        f"Result: backward ≤ one forward iteration and peak memory ≤ 1.5x on "
        f"{sum(verdicts)} of {len(verdicts)} problems.",
    ])
    emit_report(text, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
