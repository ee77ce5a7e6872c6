"""Pose-graph optimisation benchmark: default ``jaxpose pgo`` vs GTSAM 4.3 on every g2o file.

Same files, same problem (first pose fixed, cost 0.5·Σ rᵀΩr with r = Log(Z⁻¹·Xi⁻¹·Xj)),
same stopping rule (relative decrease 1e-10, absolute 1e-12, at most ``--max-steps``
iterations), one run. Each contestant runs each file in its own subprocess, so the peak
resident memory (``getrusage`` ru_maxrss, read at the end of the subprocess) is that
contestant's alone; the process baseline (Python + imports, measured before the file is
read) is printed too.

* jaxpose, as ``jaxpose pgo FILE`` runs it: ``initial_poses(graph, "auto")`` (chordal
  relaxation on the host unless the file's poses cost less), then ``pose_graph_problem`` +
  ``solve`` under ``jax.jit``; on graphs of at most 600 tangent dimensions
  (``start_in_solve``) the same relaxation and choice run inside the compiled solve
  (``solve_from_start``), whose time then includes them (init column "in the solve").
  Reported: initialisation time, compile time (trace, lower and XLA compile with the
  CLI's compiler options and XLA flags, ``WHOLE_LOOP_FLAGS``), steady-state solve time (all
  iterations, the problem held on the device and called through ``jax.jit``'s dispatch,
  best of ``--repeats`` after a warm-up run), total = initialisation +
  solve (compilation reported separately), time per iteration = solve / iterations.
  The time per iteration is split into the host sparse Cholesky (CHOLMOD numeric
  factorisation + solve, timed inside the callback) and the rest (linearisation, CSR
  assembly, device↔host transfer, retraction, bookkeeping), as measured in the best run.
* GTSAM, two paths, each with a ``PriorFactorPose3/Pose2`` (σ = 1e-6) on the first pose
  and ``LevenbergMarquardtOptimizer`` (relative/absolute error tolerance 1e-10/1e-12):
  "odometry" starts LM from the file's values as ``readG2o`` returns them; "own init"
  starts it from ``gtsam.InitializePose3.initialize`` (chordal) for 3D files and
  ``gtsam.lago.initialize`` for 2D files (lago refuses files with non-diagonal
  information: reported as such). Time = initialisation + construct the optimizer +
  ``optimize()``, best of ``--repeats``; cost = ``graph.error`` of the file's factors
  (without the prior) at the result.

The bar (issue 17): jaxpose's cost ≤ (1 + 1e-6) × the lower GTSAM cost, in less total time
than GTSAM's better path (the one with the lower cost; the faster of the two when their
costs agree to 1e-6), and on parking-garage and sphere2500 a time per iteration ≤ 1x
GTSAM's (against GTSAM's LM from odometry, the same iterations on both sides).

Iteration counts differ in meaning: jaxpose counts every LM trial (accepted or not), GTSAM
its outer iterations. Absolute times on a shared machine are noisy; the ratios from one
run are what count, and the load average is printed with the table. Every timed loop
(initialisation, solve, both GTSAM paths) runs ``--repeats`` times and, where those take
under ``MIN_TIMED_S``, on until it has (at most ``MAX_RUNS``): the tiny graphs' calls take
a fraction of a millisecond. A missing GTSAM is reported as skipped, never faked.

Usage::

    python bench/pgo.py [--quick] [--files tinyGrid3D,parking-garage,...] [--solver sparse]
                        [--float32] [--repeats 3] [--max-steps 200] [--out FILE.md]
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # run as a script: make `bench` and `jaxpose` importable
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bench._common import (
    ROOT,
    fmt_ratio,
    fmt_seconds,
    import_peer,
    markdown_table,
    package_version,
    parser,
    spawn_worker,
    worker_result,
)

DATA = ROOT.parent / "shared" / "data" / "g2o"
# every pose graph of the shared folder (g2o files and the two g2o-format examples)
DEFAULT_FILES = tuple(sorted(p.stem for p in [*DATA.glob("*.g2o"), *DATA.glob("*.txt")]
                             if p.is_file())) or ("tinyGrid3D",)
QUICK_FILES = ("tinyGrid3D", "smallGrid3D", "intel", "parking-garage", "sphere2500")
# GTSAM LM final costs listed in ../shared/data/README.md (odometry start)
README_COST = {
    "tinyGrid3D": 9.313909, "smallGrid3D": 5.179253e2, "parking-garage": 6.341924e-1,
    "sphere2500": 6.757010e2, "intel": 2.250212e1,
}
# The bars: issue 17 (cost ≤ (1 + 1e-6) × GTSAM's lower cost in less total time;
# time per iteration ≤ 1x GTSAM's on garage and sphere2500); issue 4 (compile < 30 s,
# garage RSS < 3 GiB)
BAR_RATIO_FILES = ("parking-garage", "sphere2500")
BAR_ITER_RATIO, BAR_COST_RTOL = 1.0, 1e-6
BAR_COMPILE_S, BAR_GARAGE_RSS = 30.0, 3 * 2**30
BAR_GARAGE_COMPILE_S = 3.0  # issue 17: the CLI's cold start on parking-garage


MIN_TIMED_S, MAX_RUNS = 0.25, 200


def _runs(repeats: int, times: list[float]) -> Iterator[int]:
    """Run indices for a timed loop that appends to ``times``: at least ``repeats`` runs,
    more (up to MAX_RUNS) until MIN_TIMED_S seconds are timed — the best of three runs of
    a sub-millisecond call (the tiny graphs, both contestants) is mostly noise."""
    k = 0
    while k < max(1, repeats) or (sum(times) < MIN_TIMED_S and k < MAX_RUNS):
        yield k
        k += 1


def _path(name: str) -> Path:
    p = Path(name)
    if p.suffix and p.is_file():
        return p
    for cand in (DATA / name, DATA / f"{name}.g2o", DATA / f"{name}.txt"):
        if cand.is_file():
            return cand
    return DATA / f"{name}.g2o"


def _peak_rss() -> int:
    """Peak resident set size of this process in bytes (Linux reports KiB)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss if sys.platform == "darwin" else rss * 1024


# ----------------------------------------------------------------------------------
# Workers (run in a subprocess each)
# ----------------------------------------------------------------------------------
def run_jaxpose(path: Path, solver: str, float32: bool, repeats: int, max_steps: int) -> dict:
    import jax

    jax.config.update("jax_enable_x64", not float32)
    import jax.numpy as jnp

    from jaxpose import compile_options, read_g2o
    from jaxpose.graph import _linear as linear
    from jaxpose.graph import _pgo as pgo
    from jaxpose.graph import initial_poses, solve
    from jaxpose.optim import Stopping

    # profile: time each host sparse factorisation (CHOLMOD) the solve calls back into;
    # installed before tracing (the callback is captured then); costs microseconds
    host_calls: list[float] = []
    factorise = linear._cholmod_solve

    def timed_factorise(*a):  # noqa: ANN002, ANN202
        t0 = time.perf_counter()
        out = factorise(*a)
        host_calls.append(time.perf_counter() - t0)
        return out

    linear._cholmod_solve = timed_factorise
    baseline = _peak_rss()
    graph = read_g2o(path)
    dtype = jnp.float32 if float32 else jnp.float64
    init_times = []
    stopping = Stopping(max_steps=max_steps, cost_rtol=1e-10, cost_atol=1e-12, gtol=0.0,
                        xtol=0.0)
    in_solve = pgo.start_in_solve(graph, "auto")
    if in_solve:  # the CLI's path: the initialisation is part of the timed solve
        start, init_times = None, [0.0]

        def run(p):  # noqa: ANN001, ANN202
            return pgo.solve_from_start(p, "auto", linear_solver=solver, stopping=stopping)
    else:
        for _ in _runs(repeats, init_times):
            t0 = time.perf_counter()
            start, method = initial_poses(graph, "auto")
            init_times.append(time.perf_counter() - t0)

        def run(p):  # noqa: ANN001, ANN202
            return solve(p, linear_solver=solver, stopping=stopping), None
    t0 = time.perf_counter()
    # on the device once, as a user solving repeatedly would hold it (NumPy index arrays
    # would be copied in on every call)
    problem = jax.device_put(pgo.pose_graph_problem(graph, dtype=dtype, poses=start))
    jax.block_until_ready(problem)
    build_s = time.perf_counter() - t0
    # the CLI's compiler options; compiling through the jitted function fills its cache,
    # so the timed calls take jit's C++ dispatch (an AOT executable's Python call path
    # costs ~0.3 ms, the whole solve of a tiny graph)
    compiled = jax.jit(run, compiler_options=compile_options())
    t0 = time.perf_counter()
    compiled.lower(problem).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol, chordal = jax.block_until_ready(compiled(problem))  # first run (warm-up)
    first_s = time.perf_counter() - t0
    if in_solve:
        method = f"{'chordal' if bool(chordal) else 'odometry'}, in the solve"
    times, host = [], []
    for _ in _runs(repeats, times):
        host_calls.clear()
        t0 = time.perf_counter()
        sol, _ = jax.block_until_ready(compiled(problem))
        times.append(time.perf_counter() - t0)
        host.append(sum(host_calls))
    best = int(min(range(len(times)), key=times.__getitem__)) if times else 0
    return dict(
        host_factor_s=host[best] if host_calls else None, host_factor_calls=len(host_calls),
        poses=int(graph.n_poses), edges=int(graph.n_edges), kind=graph.kind,
        build_s=build_s, compile_s=compile_s, first_s=first_s, steady_s=min(times),
        init_s=min(init_times), init=method, total_s=min(init_times) + min(times),
        times=times, iterations=int(sol.iterations), status=sol.status_name,
        initial_cost=float(sol.initial_cost), cost=float(sol.cost),
        linear_iterations=int(sol.linear_iterations), baseline_rss=baseline,
        peak_rss=_peak_rss(), version=package_version("jaxpose"), jax=jax.__version__,
        backend=jax.default_backend(), blas=_cholmod_blas(),
    )


def _gtsam_lm(gtsam: Any, full: Any, initial: Any, max_steps: int) -> tuple[Any, int]:
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    params.setMaxIterations(max_steps)
    opt = gtsam.LevenbergMarquardtOptimizer(full, initial, params)
    return opt.optimize(), int(opt.iterations())


def run_gtsam(path: Path, repeats: int, max_steps: int) -> dict:
    import numpy as np

    peer = import_peer("gtsam")
    if not peer.available:
        return dict(skipped=peer.reason)
    gtsam = peer.module

    baseline = _peak_rss()
    with open(path) as fh:  # readG2o needs to be told 2D or 3D
        is3d = any(line.startswith("VERTEX_SE3") or line.startswith("EDGE_SE3") for line in fh)
    graph, initial = gtsam.readG2o(str(path), is3d)
    full = gtsam.NonlinearFactorGraph(graph)  # the file's factors + a prior on pose 0
    first = int(initial.keys()[0]) if hasattr(initial, "keys") else 0
    if is3d:
        full.add(gtsam.PriorFactorPose3(first, initial.atPose3(first),
                                        gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6))))
        own_name, own_init = "chordal", lambda: gtsam.InitializePose3.initialize(full)
    else:
        full.add(gtsam.PriorFactorPose2(first, initial.atPose2(first),
                                        gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-6))))
        own_name, own_init = "lago", lambda: gtsam.lago.initialize(full)
    out: dict[str, Any] = dict(
        poses=int(initial.size()), edges=int(graph.size()),
        initial_cost=float(graph.error(initial)), version=package_version("gtsam"),
        own_name=own_name,
    )
    # path 1: LM from the file's values
    times, result, iterations = [], None, 0
    for _ in _runs(repeats, times):
        t0 = time.perf_counter()
        result, iterations = _gtsam_lm(gtsam, full, initial, max_steps)
        times.append(time.perf_counter() - t0)
    out.update(steady_s=min(times), times=times, iterations=iterations,
               cost=float(graph.error(result)), cost_with_prior=float(full.error(result)))
    # path 2: GTSAM's own initialisation, then LM
    try:
        times, init_times = [], []
        for _ in _runs(repeats, times):
            t0 = time.perf_counter()
            start = own_init()
            t1 = time.perf_counter()
            result, iterations = _gtsam_lm(gtsam, full, start, max_steps)
            times.append(time.perf_counter() - t0)
            init_times.append(t1 - t0)
        out.update(own_s=min(times), own_init_s=min(init_times), own_iterations=iterations,
                   own_cost=float(graph.error(result)))
    except Exception as err:  # noqa: BLE001 - lago refuses full information matrices
        out["own_failed"] = f"{type(err).__name__}: {str(err).splitlines()[0][:60]}"
    out.update(baseline_rss=baseline, peak_rss=_peak_rss())
    return out


def _cholmod_blas() -> str:
    from jaxpose.graph import _cholmod

    return _cholmod.blas() if _cholmod.available() else "—"


def _worker(args: argparse.Namespace) -> int:
    path = Path(args.file)
    try:
        if args.worker == "jaxpose":
            from jaxpose._compile import use_whole_loops

            use_whole_loops()  # the jaxpose command's XLA flags, before JAX starts its backend
            out = run_jaxpose(path, args.solver, args.float32, args.repeats, args.max_steps)
        else:
            out = run_gtsam(path, args.repeats, args.max_steps)
    except ImportError as err:
        out = dict(skipped=f"{err.name or err} not installed")
    worker_result(out)
    return 0


def _spawn(contestant: str, path: Path, args: argparse.Namespace) -> dict:
    cmd = [str(Path(__file__).resolve()), "--worker", contestant,
           "--file", str(path), "--solver", args.solver, "--repeats", str(args.repeats),
           "--max-steps", str(args.max_steps)]
    if args.float32:
        cmd.append("--float32")
    return spawn_worker(cmd, timeout=args.timeout)


# ----------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------
def _gib(b: int | None) -> str:
    if b is None:
        return "—"
    return f"{b / 2**30:.2f} GiB" if b >= 2**30 else f"{b / 2**20:.0f} MiB"


def _cost(x: float | None) -> str:
    return "—" if x is None else f"{x:.7g}"


def _status(r: dict) -> str | None:
    return r.get("skipped") and f"skipped: {r['skipped']}" or r.get("failed") and (
        f"failed: {r['failed']}")


def _better_gtsam(gt: dict) -> tuple[str, float, float] | None:
    """(path name, cost, time) of GTSAM's better path: the lower cost, the faster of the two
    when the costs agree to 1e-6."""
    paths = []
    if "cost" in gt:
        paths.append(("odometry", gt["cost"], gt["steady_s"]))
    if "own_cost" in gt:
        paths.append((gt.get("own_name", "own"), gt["own_cost"], gt["own_s"]))
    if not paths:
        return None
    low = min(c for _, c, _ in paths)
    tied = [p for p in paths if p[1] <= low * (1 + BAR_COST_RTOL) + 1e-300]
    return min(tied, key=lambda p: p[2])


def _per_iter(r: dict, time_key: str = "steady_s", it_key: str = "iterations") -> float | None:
    t, k = r.get(time_key), r.get(it_key)
    return t / k if t is not None and k else None


def _checks(name: str, jp: dict, gt: dict) -> list[str]:
    """The bar's checks for one file (issue 17, plus issue 4's compile and RSS)."""
    checks = []
    best = _better_gtsam(gt)
    if best is None:
        checks.append("vs GTSAM: " + (_status(gt) or "no GTSAM result"))
    else:
        low = min(c for c in (gt.get("cost"), gt.get("own_cost")) if c is not None)
        excess = jp["cost"] / low - 1.0
        checks.append(f"cost {excess:+.1e} vs GTSAM's lower (≤ {BAR_COST_RTOL:.0e}): "
                      + ("pass" if excess <= BAR_COST_RTOL else "FAIL"))
        ratio = jp["total_s"] / best[2]
        checks.append(f"total {ratio:.2f}x GTSAM {best[0]} (< 1x): "
                      + ("pass" if ratio < 1.0 else "FAIL"))
        if name in BAR_RATIO_FILES and "cost" in gt:
            it = _per_iter(jp) / _per_iter(gt)
            checks.append(f"per iteration {it:.2f}x GTSAM (≤ {BAR_ITER_RATIO:.0f}x): "
                          + ("pass" if it <= BAR_ITER_RATIO else "FAIL"))
    bar_compile = BAR_GARAGE_COMPILE_S if name == "parking-garage" else BAR_COMPILE_S
    checks.append(f"compile {jp['compile_s']:.2f} s (≤ {bar_compile:.0f} s): "
                  + ("pass" if jp["compile_s"] <= bar_compile else "FAIL"))
    if name == "parking-garage":
        checks.append(f"peak RSS {_gib(jp['peak_rss'])} (< 3 GiB): "
                      + ("pass" if jp["peak_rss"] < BAR_GARAGE_RSS else "FAIL"))
    return checks


def report(results: dict[str, dict[str, dict]], args: argparse.Namespace,
           load: tuple[tuple[float, ...], tuple[float, ...]]) -> str:
    import platform

    lines = [
        "# Pose-graph optimisation: jaxpose vs GTSAM",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} CPU cores; load average "
        f"(1/5/15 min) {' '.join(f'{x:.2f}' for x in load[0])} at the start, "
        f"{' '.join(f'{x:.2f}' for x in load[1])} at the end.",
    ]
    jp_any = next((r["jaxpose"] for r in results.values() if "cost" in r["jaxpose"]), {})
    gt_any = next((r["gtsam"] for r in results.values() if "cost" in r["gtsam"]), None)
    gt_skip = next((_status(r["gtsam"]) for r in results.values() if _status(r["gtsam"])), "")
    lines.append(
        f"jaxpose {jp_any.get('version', '?')} (jax {jp_any.get('jax', '?')}, "
        f"{jp_any.get('backend', '?')}), default `jaxpose pgo` (init auto), linear solver "
        f"`{args.solver}` (CHOLMOD's BLAS: {jp_any.get('blas', '?')}), "
        f"{'float32' if args.float32 else 'float64'}; "
        + (f"GTSAM {gt_any['version']}" if gt_any else f"GTSAM {gt_skip or 'not run'}")
        + f"; max {args.max_steps} iterations, best of {args.repeats} runs (of up to "
        f"{MAX_RUNS} where {args.repeats} take under {MIN_TIMED_S} s)."
    )
    lines.append("")
    header = ["file", "poses / edges", "jaxpose init", "jaxpose compile", "jaxpose solve",
              "jaxpose total", "GTSAM odometry", "GTSAM own init", "total / GTSAM better",
              "iterations (jaxpose / odometry / own)", "cost jaxpose", "cost GTSAM odometry",
              "cost GTSAM own init", "jaxpose / lower GTSAM − 1", "status"]
    rows = []
    for name, r in results.items():
        jp, gt = r["jaxpose"], r["gtsam"]
        jp_ok, gt_ok = "cost" in jp, "cost" in gt
        size = (f"{jp['poses']} / {jp['edges']}" if jp_ok
                else f"{gt['poses']} / {gt['edges']}" if gt_ok else "—")
        best = _better_gtsam(gt) if gt_ok else None
        low = (min(c for c in (gt.get("cost"), gt.get("own_cost")) if c is not None)
               if gt_ok else None)
        own = (f"{gt.get('own_name')}: {fmt_seconds(gt['own_s'])}" if "own_s" in gt
               else f"{gt.get('own_name', '')} failed: {gt['own_failed']}" if "own_failed" in gt
               else "—")
        rows.append([
            name, size,
            (jp["init"] if "in the solve" in jp["init"]
             else f"{jp['init']}: {fmt_seconds(jp['init_s'])}") if jp_ok else _status(jp),
            fmt_seconds(jp.get("compile_s")), fmt_seconds(jp.get("steady_s")),
            fmt_seconds(jp.get("total_s")),
            fmt_seconds(gt.get("steady_s")) if gt_ok else _status(gt), own,
            fmt_ratio(jp.get("total_s"), best[2] if best else None),
            f"{jp.get('iterations', '—')} / {gt.get('iterations', '—')} / "
            f"{gt.get('own_iterations', '—')}",
            _cost(jp.get("cost")), _cost(gt.get("cost")), _cost(gt.get("own_cost")),
            "—" if not (jp_ok and low) else f"{jp['cost'] / low - 1:+.1e}",
            jp.get("status", "—"),
        ])
    lines.append(markdown_table(header, rows))
    lines += ["", "Time per iteration (solve time / iterations) and peak memory:", ""]
    rows2 = []
    for name, r in results.items():
        jp, gt = r["jaxpose"], r["gtsam"]
        a, b = _per_iter(jp), _per_iter(gt)
        c = _per_iter(gt, "own_s", "own_iterations")
        hf, calls = jp.get("host_factor_s"), jp.get("host_factor_calls")
        split = (f"{hf / calls * 1e3:.0f} ms ({hf / jp['steady_s']:.0%}) / "
                 f"{(jp['steady_s'] - hf) / jp['iterations'] * 1e3:.0f} ms"
                 if hf is not None and calls and jp.get("iterations") else "— (dense)")
        rows2.append([name, fmt_seconds(a), split, fmt_seconds(b), fmt_ratio(a, b),
                      fmt_seconds(c), _gib(jp.get("peak_rss")), _gib(gt.get("peak_rss"))])
    lines.append(markdown_table(["file", "jaxpose s/it", "of which: host CHOLMOD per call "
                                 "(share) / the rest per iteration", "GTSAM odometry s/it",
                                 "ratio", "GTSAM own init s/it (incl. init)",
                                 "peak RSS jaxpose", "peak RSS GTSAM"], rows2))
    base = [r["jaxpose"].get("baseline_rss") for r in results.values()]
    base = [b for b in base if b]
    gbase = [r["gtsam"].get("baseline_rss") for r in results.values()]
    gbase = [b for b in gbase if b]
    lines += ["", "Peak RSS includes the process baseline (Python + imports, before reading "
              f"the file): jaxpose {_gib(max(base)) if base else '—'}, GTSAM "
              f"{_gib(max(gbase)) if gbase else '—'}."]
    lines += ["", "## The issue's bar", ""]
    bar_rows, verdicts = [], []
    for name, r in results.items():
        jp, gt = r["jaxpose"], r["gtsam"]
        if "cost" not in jp:
            continue
        checks = _checks(name, jp, gt)
        if name in README_COST:
            rel = abs(jp["cost"] - README_COST[name]) / README_COST[name]
            checks.append(f"cost vs README {rel:.1e} (≤ 1e-5): "
                          + ("pass" if rel <= 1e-5 else "FAIL"))
        bar_rows.append([name, "; ".join(checks)])
        fails = [c.split(":")[0].split(" (")[0] for c in checks if c.endswith("FAIL")]
        verdicts.append(f"{name} " + ("met" if not fails else "NOT met (" + ", ".join(fails)
                                                              + ")"))
    lines.append(markdown_table(["file", "checks"], bar_rows))
    failed = sum(row[1].count("FAIL") for row in bar_rows)
    fails = "1 check fails" if failed == 1 else f"{failed} checks fail"
    lines += ["", f"Result: bar {'met' if not failed else f'NOT met ({fails})'}; "
              f"per graph: {', '.join(verdicts) or 'nothing run'}"]
    lines += ["", "jaxpose iterations count every LM trial (accepted or rejected); GTSAM's "
              "count outer iterations. Solve = one whole solve after compilation; total = "
              "initialisation + solve (GTSAM: initialisation + optimizer construction + "
              "optimize)."]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = parser(__doc__, quick="the five reference graphs, one timed run (smoke run)",
               threads=False, workers=True)
    p.add_argument("--files", default=None,
                   help="comma-separated names in ../shared/data/g2o (or paths); default: "
                        "every pose graph there (--quick: " + ",".join(QUICK_FILES) + ")")
    p.add_argument("--solver", default="auto", choices=["auto", "sparse", "pcg", "dense"],
                   help="jaxpose's linear solver (default: auto, as jaxpose pgo)")
    p.add_argument("--float32", action="store_true", help="jaxpose in float32")
    p.add_argument("--repeats", type=int, default=None,
                   help="timed runs after the warm-up (default 3, --quick 1)")
    p.add_argument("--max-steps", type=int, default=200)
    p.add_argument("--contestants", default="jaxpose,gtsam")
    p.add_argument("--worker", choices=["jaxpose", "gtsam"], help=argparse.SUPPRESS)
    p.add_argument("--file", help=argparse.SUPPRESS)
    return p


def main(argv: Sequence[str] | None = None) -> str:
    args = build_parser().parse_args(argv)
    if args.repeats is None:
        args.repeats = 1 if args.quick else 3
    if args.files is None:
        args.files = ",".join(QUICK_FILES if args.quick else DEFAULT_FILES)
    if args.worker:
        _worker(args)
        return ""
    load0 = os.getloadavg()
    contestants = [c.strip() for c in args.contestants.split(",") if c.strip()]
    results: dict[str, dict[str, Any]] = {}
    for name in [f.strip() for f in args.files.split(",") if f.strip()]:
        path = _path(name)
        key = Path(name).stem
        if not path.is_file():
            missing = dict(skipped=f"{path} not found")
            results[key] = {"jaxpose": missing, "gtsam": missing}
            continue
        results[key] = {}
        for c in ("jaxpose", "gtsam"):
            if c in contestants:
                results[key][c] = _spawn(c, path, args)
            else:
                results[key][c] = dict(skipped="not selected (--contestants)")
            r = results[key][c]
            print(f"[{key} {c}] " + (
                f"{fmt_seconds(r.get('total_s', r['steady_s']))}, cost {r['cost']:.7g}"
                + (f"; own init {fmt_seconds(r['own_s'])}, cost {r['own_cost']:.7g}"
                   if "own_cost" in r else "") if "cost" in r
                else _status(r) or "?"), file=sys.stderr, flush=True)
    text = report(results, args, (load0, os.getloadavg()))
    if args.out:
        Path(args.out).write_text(text + "\n", encoding="utf-8")
    return text


if __name__ == "__main__":
    out = main()
    if out:
        print(out)
