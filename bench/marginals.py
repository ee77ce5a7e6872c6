"""Marginal covariances: all pose marginals, jaxpose vs GTSAM ``Marginals``, same run.

For each g2o file: jaxpose solves the pose graph (first pose fixed; not timed), then both
libraries compute the marginal covariance of every pose at that solution.

* jaxpose: ``jaxpose.graph.marginals(problem, solution, "pose", method=...)`` under
  ``jax.jit`` (linearisation, assembly of H, CHOLMOD's supernodal factorisation and the
  selected inversion on the host); compile time and steady-state time (best of repeats)
  reported separately.
* GTSAM: ``Marginals(graph, values)`` (linearisation + multifrontal factorisation) plus
  ``marginalCovariance(key)`` for every pose, on ``readG2o``'s graph plus a
  ``PriorFactorPose3/2`` with σ = 1e-6 on the first pose (GTSAM cannot hold a variable
  fixed); best of repeats.

The "max rel. diff" column compares the two results after mapping charts (jaxpose se3
``[ρ, φ]`` → GTSAM ``[ω, v]``); it is not exactly zero because GTSAM's gauge is a tight
prior instead of a fixed pose (the exact 1e-9 comparisons with identical priors are in
tests/graph/test_marginals.py). Absolute times on a shared machine are noisy; the ratios
in one run are what count.

Usage::

    python bench/marginals.py [--files parking-garage,sphere2500,intel] [--method sparse]
                              [--repeats 3] [--quick] [--out FILE.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `bench` and `jaxpose` importable
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from bench._common import (  # noqa: E402
    environment,
    fmt_ratio,
    fmt_seconds,
    import_peer,
    markdown_table,
    parser,
    time_callable,
    time_jax,
)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "g2o"
DEFAULT_FILES = ("parking-garage", "sphere2500", "intel")
QUICK_FILES = ("tinyGrid3D", "pose2example")
BAR_FILE = "sphere2500"  # the bar: all pose marginals in at most GTSAM's time


def _path(name: str) -> Path:
    for cand in (DATA / f"{name}.g2o", DATA / f"{name}.txt", Path(name)):
        if cand.is_file():
            return cand
    return DATA / f"{name}.g2o"


def _gtsam_values(gtsam, kind: str, poses: np.ndarray):
    vals = gtsam.Values()
    for k, p in enumerate(poses):
        if kind == "SE3":
            vals.insert(k, gtsam.Pose3(gtsam.Rot3.Quaternion(p[6], p[3], p[4], p[5]), p[:3]))
        else:
            vals.insert(k, gtsam.Pose2(p[0], p[1], np.arctan2(p[3], p[2])))
    return vals


def run_file(name: str, method: str, repeats: int, gtsam) -> dict:
    from jaxpose import read_g2o
    from jaxpose.graph import _pgo as pgo
    from jaxpose.graph import default_stopping, marginals, se3_to_gtsam, solve

    path = _path(name)
    if not path.is_file():
        return dict(skipped=f"{path} not found")
    pg = read_g2o(path)
    problem = pgo.pose_graph_problem(pg)
    t0 = time.perf_counter()
    sol = jax.block_until_ready(
        jax.jit(lambda p: solve(p, linear_solver="sparse",
                                stopping=default_stopping(200)))(problem))
    solve_s = time.perf_counter() - t0
    values = sol.variables
    fn = lambda prob, vals: marginals(prob, vals, "pose", method=method).covariances["pose"]  # noqa: E731
    timing, cov = time_jax(fn, problem, values, repeats=repeats, min_time=0.0, max_time=30.0)
    cov = np.asarray(cov)
    out = dict(poses=pg.n_poses, edges=pg.n_edges, kind=pg.kind, solve_s=solve_s,
               status=sol.status_name, compile_s=timing.compile_s, jaxpose_s=timing.best)
    if gtsam is None:
        return out
    graph, _ = gtsam.readG2o(str(path), pg.kind == "SE3")
    vals = _gtsam_values(gtsam, pg.kind, np.asarray(values["pose"].data))
    full = gtsam.NonlinearFactorGraph(graph)
    d = 6 if pg.kind == "SE3" else 3
    prior = gtsam.PriorFactorPose3 if pg.kind == "SE3" else gtsam.PriorFactorPose2
    at = vals.atPose3(0) if pg.kind == "SE3" else vals.atPose2(0)
    full.add(prior(0, at, gtsam.noiseModel.Isotropic.Sigma(d, 1e-6)))
    keys = list(range(pg.n_poses))

    def all_marginals():
        m = gtsam.Marginals(full, vals)
        return [m.marginalCovariance(k) for k in keys]

    gt_timing, ref = time_callable(all_marginals, repeats=repeats, min_time=0.0, max_time=30.0)
    mine = se3_to_gtsam(cov) if pg.kind == "SE3" else cov
    rel = max(np.abs(mine[k] - ref[k]).max() / np.abs(ref[k]).max() for k in keys[1:])
    out.update(gtsam_s=gt_timing.best, max_rel_diff=float(rel))
    return out


def report(results: dict[str, dict], args: argparse.Namespace, gtsam_label: str) -> str:
    lines = ["# Marginal covariances: jaxpose vs GTSAM", "",
             f"{environment()}; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}",
             f"jaxpose method `{args.method}` (float64); {gtsam_label}; best of "
             f"{args.repeats} runs each.", ""]
    header = ["file", "poses / edges", "jaxpose compile", "jaxpose all marginals",
              "GTSAM all marginals", "ratio (jaxpose / GTSAM)", "max rel. diff"]
    rows = []
    for name, r in results.items():
        if "skipped" in r:
            rows.append([name, f"skipped: {r['skipped']}", "—", "—", "—", "—", "—"])
            continue
        rows.append([name, f"{r['poses']} / {r['edges']}", fmt_seconds(r["compile_s"]),
                     fmt_seconds(r["jaxpose_s"]), fmt_seconds(r.get("gtsam_s")),
                     fmt_ratio(r["jaxpose_s"], r.get("gtsam_s")),
                     f"{r['max_rel_diff']:.1e}" if "max_rel_diff" in r else "—"])
    lines.append(markdown_table(header, rows))
    bar = results.get(BAR_FILE, {})
    if "gtsam_s" in bar:
        ok = bar["jaxpose_s"] <= bar["gtsam_s"]
        verdict = (f"{BAR_FILE} all {bar['poses']} pose marginals in "
                   f"{fmt_seconds(bar['jaxpose_s'])} vs GTSAM {fmt_seconds(bar['gtsam_s'])} "
                   f"({fmt_ratio(bar['jaxpose_s'], bar['gtsam_s'])}): bar "
                   + ("met" if ok else "NOT met"))
    else:
        verdict = f"{BAR_FILE} not compared (not run, or GTSAM skipped): bar not checked"
    ratios = [f"{n} {fmt_ratio(r['jaxpose_s'], r['gtsam_s'])}" for n, r in results.items()
              if "gtsam_s" in r]
    lines += ["", f"Result: {verdict}; time / GTSAM's: {', '.join(ratios) or '—'}"]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = parser(__doc__, quick="small files only (smoke run)", threads=False)
    p.add_argument("--files", default=None, help="comma-separated names in ../shared/data/g2o")
    p.add_argument("--method", default="sparse", choices=["auto", "sparse", "dense", "pcg"])
    p.add_argument("--repeats", type=int, default=3)
    return p


def main(argv: Sequence[str] | None = None) -> str:
    args = build_parser().parse_args(argv)
    files = (args.files.split(",") if args.files
             else QUICK_FILES if args.quick else DEFAULT_FILES)
    peer = import_peer("gtsam")
    gtsam = peer.module if peer.available else None
    results = {}
    for name in (f.strip() for f in files if f.strip()):
        results[name] = run_file(name, args.method, args.repeats, gtsam)
        r = results[name]
        print(f"[{name}] " + ("skipped" if "skipped" in r else
                              f"jaxpose {fmt_seconds(r['jaxpose_s'])}, GTSAM "
                              f"{fmt_seconds(r.get('gtsam_s'))}"), file=sys.stderr, flush=True)
    text = report(results, args, peer.label())
    if args.out:
        Path(args.out).write_text(text + "\n", encoding="utf-8")
    return text


if __name__ == "__main__":
    print(main())
