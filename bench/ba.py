"""Bundle-adjustment benchmark: jaxpose LM with Schur elimination vs the plain path, and GTSAM.

Problems: the BAL files in ../shared/data/bal and a synthetic BAL problem
(``jaxpose.datasets.synthetic_bal``: cameras on a ring, points in the unit ball, each seen
by ``--obs`` consecutive cameras, Gaussian pixel noise σ = ``--noise``; default 50 cameras,
10 000 points). Every camera has 9 free parameters (pose, f, k1, k2); nothing is fixed
(the 7-dof gauge is left to LM's damping, as in Ceres). Cost 0.5·Σ‖r‖² in pixels².

* jaxpose (float64, jit): ``bundle_adjustment_problem`` + ``solve`` with Marquardt damping
  (λ·diag H), λ₀ = 1e-4, Nielsen's rule (Ceres' LM), relative decrease 1e-10, at most
  ``--max-steps`` iterations; linear solvers ``schur`` (points eliminated, reduced camera
  system dense or CHOLMOD) and ``sparse`` (the plain path: the full normal equations with
  CHOLMOD). Compile time (lower + XLA compile) and steady-state time (one whole solve)
  are reported separately.
* GTSAM 4.3 (if installed): ``SfmData.FromBalFile`` of the same file,
  ``GeneralSFMFactorCal3Bundler`` (σ = 1 px), ``LevenbergMarquardtOptimizer`` with
  diagonal damping, λ₀ = 1e-4, the same tolerance and iteration budget; its initial error
  is checked against jaxpose's initial cost (same problem, same conventions).

The jaxpose solvers run interleaved in one process (``--repeats`` rounds, best time each),
so load changes on a shared machine hit them alike; GTSAM runs right after them in its own
subprocess (its TBB worker threads would otherwise keep spinning next to XLA's). The
ratios within one run are what count. The noise
floor of the synthetic problem is the expected RMSE at the optimum,
σ·√((M − P + 7)/M) for M residuals and P parameters. A missing GTSAM is reported as
skipped, never faked.

Usage::

    python bench/ba.py [--quick] [--cameras 50 --points 10000 --obs 5 --noise 1.0]
                       [--files dubrovnik-1-1-pre,...] [--solvers schur,sparse]
                       [--repeats 3] [--max-steps 200] [--out FILE.md]
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from collections.abc import Sequence
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

DATA = ROOT.parent / "shared" / "data" / "bal"
DEFAULT_FILES = ("dubrovnik-1-1-pre", "dubrovnik-3-7-18-pre", "dubrovnik-3-7-pre")
SOLVERS = ("schur", "sparse", "pcg", "dense")


def _jaxpose_runner(problem: Any, solver: str, max_steps: int) -> tuple[float, Any]:
    """(compile seconds, run) for one linear solver; ``run()`` returns the solution."""
    import jax

    from jaxpose.graph import _ba as ba
    from jaxpose.graph import solve
    from jaxpose.optim import Nielsen, Stopping

    graph = ba.bundle_adjustment_problem(problem, eliminate=solver == "schur")
    stopping = Stopping(max_steps=max_steps, cost_rtol=1e-10, gtol=0.0, xtol=0.0)
    fn = jax.jit(lambda g: solve(g, linear_solver=solver, damping="diagonal",
                                 strategy=Nielsen(1e-4), stopping=stopping))
    t0 = time.perf_counter()
    compiled = fn.lower(graph).compile()
    compile_s = time.perf_counter() - t0
    return compile_s, lambda: jax.block_until_ready(compiled(graph))


def _gtsam_runner(gtsam: Any, path: str, max_steps: int) -> tuple[float, Any]:
    """(initial error, run) for GTSAM's LM on a BAL file; ``run()`` → (result, iterations)."""
    from gtsam.symbol_shorthand import C, P

    sfm = gtsam.SfmData.FromBalFile(path)
    noise = gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for i in range(sfm.numberCameras()):
        initial.insert(C(i), sfm.camera(i))
    for j in range(sfm.numberTracks()):
        track = sfm.track(j)
        initial.insert(P(j), track.point3())
        for k in range(track.numberMeasurements()):
            i, uv = track.measurement(k)
            graph.add(gtsam.GeneralSFMFactorCal3Bundler(uv, noise, C(i), P(j)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(max_steps)
    params.setlambdaInitial(1e-4)
    params.setDiagonalDamping(True)

    def run():
        opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        result = opt.optimize()
        return graph.error(result), int(opt.iterations())

    return float(graph.error(initial)), run




def _gtsam_worker(path: str, repeats: int, max_steps: int) -> dict[str, Any]:
    peer = import_peer("gtsam")
    if not peer.available:
        return dict(skipped=peer.reason)
    initial, run = _gtsam_runner(peer.module, path, max_steps)
    result = run()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = run()
        times.append(time.perf_counter() - t0)
    cost, its = result
    return dict(times=times, steady_s=min(times), initial_cost=initial, cost=cost,
                iterations=its, version=getattr(peer.module, "__version__", "?"))


def _spawn_gtsam(path: str, args: argparse.Namespace) -> dict[str, Any]:
    return spawn_worker([str(Path(__file__).resolve()), "--worker", "gtsam", "--file", path,
                         "--repeats", str(args.repeats), "--max-steps", str(args.max_steps)],
                        timeout=args.timeout)


def bench_problem(name: str, problem: Any, path: str, args: argparse.Namespace,
                  floor: float | None) -> dict[str, Any]:
    """Run every contestant on one problem, interleaved; returns the rows' data."""
    from jaxpose.graph import _ba as ba

    solvers = [s for s in args.solvers.split(",") if s] if "jaxpose" in args.contestants else []
    runners: dict[str, Any] = {}
    out: dict[str, Any] = {"name": name, "size": (problem.n_cameras, problem.n_points,
                                                  problem.n_observations),
                           "rmse0": ba.reprojection_rmse(problem), "floor": floor, "rows": {}}
    for s in solvers:
        try:
            compile_s, run = _jaxpose_runner(problem, s, args.max_steps)
        except Exception as err:  # noqa: BLE001 - reported in the table
            out["rows"][s] = dict(failed=f"{type(err).__name__}: {err}"[:120])
            continue
        runners[s] = run
        out["rows"][s] = dict(compile_s=compile_s, times=[])
    results: dict[str, Any] = {}
    for k, run in runners.items():  # warm-up (first call: thread pools, page faults)
        results[k] = run()
    for _ in range(args.repeats):
        for k, run in runners.items():
            t0 = time.perf_counter()
            results[k] = run()
            out["rows"][k]["times"].append(time.perf_counter() - t0)
    for k, res in results.items():
        row = out["rows"][k]
        row["steady_s"] = min(row["times"])
        row.update(cost=float(res.cost), initial_cost=float(res.initial_cost),
                   iterations=int(res.iterations), status=res.status_name,
                   rmse=ba.reprojection_rmse(problem, res.variables))
    if "gtsam" in args.contestants:
        gt = _spawn_gtsam(path, args)
        if "cost" in gt:
            gt.update(rmse=(gt["cost"] / problem.n_observations) ** 0.5, status="—")
        out["rows"]["gtsam"] = gt
    return out


def _problems(args: argparse.Namespace, tmp: str) -> list[tuple[str, Any, str, float | None]]:
    from jaxpose.datasets import synthetic_bal
    from jaxpose.io import read_bal, write_bal

    out = []
    for name in [f.strip() for f in args.files.split(",") if f.strip()]:
        path = DATA / (name if name.endswith(".txt") else f"{name}.txt")
        if path.is_file():
            out.append((Path(name).stem, read_bal(path), str(path), None))
        else:
            out.append((Path(name).stem, None, str(path), None))
    if args.cameras > 0 and args.points > 0:
        prob, _ = synthetic_bal(args.cameras, args.points, args.obs, args.noise, seed=args.seed)
        path = os.path.join(tmp, "synthetic.txt")
        write_bal(path, prob)  # GTSAM reads the same problem from this file
        m = 2 * prob.n_observations
        n_params = 9 * prob.n_cameras + 3 * prob.n_points
        floor = args.noise * ((m - n_params + 7) / m) ** 0.5
        out.append((f"synthetic {args.cameras}x{args.points}", prob, path, floor))
    return out


def _status(r: dict) -> str | None:
    if "skipped" in r:
        return f"skipped: {r['skipped']}"
    if "failed" in r:
        return f"failed: {r['failed']}"
    return None


def _cost_diff(other: float, jp: dict) -> str:
    """Relative difference of final costs; costs at rounding level (≤ 1e-20 of the initial
    cost: the data are interpolated) compare as equal."""
    tiny = 1e-20 * jp["initial_cost"]
    if max(other, jp["cost"]) <= tiny:
        return "both at rounding level (interpolated)"
    if jp["cost"] <= tiny:
        return f"jaxpose at rounding level, other {other:.3g}"
    return f"{abs(other - jp['cost']) / jp['cost']:.1e} rel. diff"


def report(results: list[dict], args: argparse.Namespace, load: tuple, version: str) -> str:
    import platform

    import jax

    lines = [
        "# Bundle adjustment: jaxpose (Schur vs plain) vs GTSAM",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} CPU cores; load average "
        f"(1/5/15 min) {' '.join(f'{x:.2f}' for x in load[0])} at the start, "
        f"{' '.join(f'{x:.2f}' for x in load[1])} at the end. jaxpose {version} (jax "
        f"{jax.__version__}, {jax.default_backend()}, float64); max {args.max_steps} "
        f"iterations, interleaved, best of {args.repeats} runs.",
        "",
    ]
    header = ["problem", "cameras / points / obs", "contestant", "compile", "steady",
              "vs schur", "iterations", "status", "final cost", "RMSE initial → final (px)",
              "noise floor"]
    rows = []
    for res in results:
        if "missing" in res:
            rows.append([res["name"], "—", "—", f"skipped: {res['missing']}"] + ["—"] * 7)
            continue
        base = res["rows"].get("schur", {}).get("steady_s")
        for k, r in res["rows"].items():
            st = _status(r)
            rows.append([
                res["name"], " / ".join(map(str, res["size"])),
                "GTSAM" if k == "gtsam" else f"jaxpose {k}",
                st or (fmt_seconds(r["compile_s"]) if "compile_s" in r else "—"),
                fmt_seconds(r.get("steady_s")), fmt_ratio(r.get("steady_s"), base),
                str(r.get("iterations", "—")), r.get("status", "—"),
                "—" if st else f"{r['cost']:.7g}",
                "—" if st else f"{res['rmse0']:.4g} → {r['rmse']:.4g}",
                "—" if res["floor"] is None else f"{res['floor']:.4f}",
            ])
    lines.append(markdown_table(header, rows))
    checks = []
    for res in results:
        rs = res.get("rows", {})
        jp = rs.get("schur", {})
        if "cost" not in jp:
            continue
        items = []
        if "steady_s" in rs.get("sparse", {}):
            ratio = rs["sparse"]["steady_s"] / jp["steady_s"]
            items.append(f"Schur {ratio:.2f}x faster than the plain (sparse) path"
                         if ratio >= 1 else f"Schur {1 / ratio:.2f}x SLOWER than the plain path")
            items.append("final cost vs plain: " + _cost_diff(rs["sparse"]["cost"], jp))
        if res["floor"] is not None:
            items.append(f"RMSE {jp['rmse']:.4f} vs noise floor {res['floor']:.4f} ("
                         f"{jp['rmse'] / res['floor'] - 1:+.1%})")
        gt = rs.get("gtsam", {})
        if "cost" in gt:
            items.append(f"GTSAM initial error {gt['initial_cost']:.7g} vs jaxpose "
                         f"{jp['initial_cost']:.7g}; final cost vs GTSAM: "
                         + _cost_diff(gt["cost"], jp)
                         + f"; jaxpose schur {gt['steady_s'] / jp['steady_s']:.2f}x GTSAM's speed")
        checks.append([res["name"], "; ".join(items)])
    lines += ["", "## Checks", "", markdown_table(["problem", "checks"], checks)]
    speedups = []
    for res in results:
        rs = res.get("rows", {})
        if "steady_s" in rs.get("schur", {}) and "steady_s" in rs.get("sparse", {}):
            ratio = rs["sparse"]["steady_s"] / rs["schur"]["steady_s"]
            gt = rs.get("gtsam", {})
            vs = (f", {gt['steady_s'] / rs['schur']['steady_s']:.2f}x GTSAM's speed"
                  if "steady_s" in gt else "")
            speedups.append(f"{res['name']}: Schur {ratio:.2f}x the plain path{vs}")
    lines += ["", "Result: " + ("; ".join(speedups[-1:]) or "no timings")]
    lines += ["", "Iterations: jaxpose counts every LM trial (accepted or rejected), GTSAM its "
              "outer iterations. Steady-state = one whole solve after compilation (GTSAM: "
              "optimizer construction + optimize). The BAL files have fewer residuals than "
              "free parameters, so their noise floor is 0. Peak RSS of this process: "
              f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10:.0f} MiB."]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = parser(__doc__, quick="small synthetic problem (20 cameras x 2000 points), 2 repeats",
               threads=False, workers=True)
    p.add_argument("--files", default=",".join(DEFAULT_FILES),
                   help="comma-separated names in ../shared/data/bal ('' for none)")
    p.add_argument("--cameras", type=int, default=50)
    p.add_argument("--points", type=int, default=10000)
    p.add_argument("--obs", type=int, default=5, help="observations per point")
    p.add_argument("--noise", type=float, default=1.0, help="pixel noise σ")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--solvers", default="schur,sparse", help=f"jaxpose linear solvers {SOLVERS}")
    p.add_argument("--contestants", default="jaxpose,gtsam")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--max-steps", type=int, default=200)
    p.add_argument("--worker", choices=["gtsam"], help=argparse.SUPPRESS)
    p.add_argument("--file", help=argparse.SUPPRESS)
    return p


def main(argv: Sequence[str] | None = None) -> str:
    args = build_parser().parse_args(argv)
    if args.worker:
        worker_result(_gtsam_worker(args.file, args.repeats, args.max_steps))
        return ""
    if args.quick:  # smaller defaults (explicit values win)
        defaults = build_parser().parse_args([])
        for name, value in (("cameras", 20), ("points", 2000), ("repeats", 2)):
            if getattr(args, name) == getattr(defaults, name):
                setattr(args, name, value)
    bad = [s for s in args.solvers.split(",") if s and s not in SOLVERS]
    if bad:
        raise SystemExit(f"--solvers: unknown {bad}; expected some of {SOLVERS}")
    import jax

    jax.config.update("jax_enable_x64", True)

    load0 = os.getloadavg()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, prob, path, floor in _problems(args, tmp):
            if prob is None:
                results.append(dict(name=name, missing=f"{path} not found"))
                continue
            res = bench_problem(name, prob, path, args, floor)
            results.append(res)
            print(f"[{name}] " + ", ".join(
                f"{k} {fmt_seconds(r['steady_s'])}" for k, r in res["rows"].items()
                if "steady_s" in r), file=sys.stderr, flush=True)
    text = report(results, args, (load0, os.getloadavg()), package_version("jaxpose"))
    if args.out:
        Path(args.out).write_text(text + "\n", encoding="utf-8")
    return text


if __name__ == "__main__":
    text = main()
    if text:
        print(text)
