"""The ``jaxpose`` command.

``jaxpose demo`` runs on built-in, generated examples (no data files needed): it checks
the Lie-group identities on random batches, times batched jitted ops, solves a synthetic
pose-averaging problem with Adam on the manifold, and optimises a synthetic noisy sphere
pose graph with the sparse Levenberg–Marquardt solver.

``jaxpose pgo FILE.g2o`` optimises a g2o pose graph (SE3 or SE2), prints the per-iteration
table and a summary, and optionally writes the optimised graph and a before/after plot.

``jaxpose ba FILE.txt`` bundle-adjusts a BAL problem (Schur elimination of the points),
prints the per-iteration table, a summary with the reprojection RMSE, and optionally
writes the optimised problem in BAL format.

Errors: every failure (a malformed file, an output directory that does not exist, a
non-finite cost, a bad option) prints one line ``jaxpose COMMAND: message`` to stderr and
exits with status 1 (2 for a bad command line), without a traceback; ``--debug`` prints the
traceback too. Output paths are checked before the input is solved, and nothing is written
when the optimised values are not finite.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import re
import sys
import time
import traceback
import warnings
from collections.abc import Callable, Sequence

EPILOG = (
    "Any failure prints one line 'jaxpose COMMAND: message' to stderr and exits with status 1 "
    "(2 for a bad command line); --debug adds the traceback."
)


class CLIError(Exception):
    """A failure the command reports as one line (no traceback)."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line usage errors (exit status 2)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _int_at_least(low: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {value}")
        return value

    return parse


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text!r}")
    return value


def _check_output(path: str | None, option: str) -> None:
    """Fail before any work if ``path`` cannot be written: its directory must exist and be
    writable, and ``path`` itself must not be a directory."""
    if not path:
        if path is not None:
            raise CLIError(f"{option}: expected a file name, got an empty string")
        return
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise CLIError(f"{option} {path}: the directory {folder} does not exist")
    if os.path.isdir(path):
        raise CLIError(f"{option} {path}: is a directory, expected a file name")
    if not os.access(folder, os.W_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
        raise CLIError(f"{option} {path}: not writable")


def _check_float32_range(arrays, what: str) -> None:
    """--float32: values beyond the float32 range would become inf."""
    import numpy as np

    big = max((float(np.max(np.abs(a))) for a in arrays if a.size), default=0.0)
    if big > float(np.finfo(np.float32).max):
        raise CLIError(f"--float32: {what} holds values up to {big:.3g}, beyond the float32 "
                       "range; run without --float32")


def _enable_x64(enable: bool) -> None:
    import jax

    jax.config.update("jax_enable_x64", enable)


def _group_checks(group, k1, k2, batch, dtype):
    """Max errors of Log∘Exp, X·X⁻¹, the adjoint identity and Jr·Jr⁻¹ (jitted, one group)."""
    import jax
    import jax.numpy as jnp

    def run(k1, k2):
        x = group.random(k1, (batch,), sigma=0.8, dtype=dtype)
        v = jax.random.normal(k2, (batch, group.tangent_dim), dtype)
        v = v * jnp.minimum(1.0, 2.5 / jnp.linalg.norm(v, axis=-1, keepdims=True))  # |a| < π
        a = group.algebra(v)
        roundtrip = jnp.max(jnp.abs(a.exp().log().data - a.data))
        eye = jnp.eye(group.matrix_dim, dtype=dtype)
        ident = jnp.max(jnp.abs((x @ x.inv()).matrix() - eye))
        adj = jnp.max(jnp.abs((x @ a.exp()).matrix() - (x.adj(a).exp() @ x).matrix()))
        jr_err = jnp.max(jnp.abs(a.jr() @ a.jr_inv() - jnp.eye(group.tangent_dim, dtype=dtype)))
        return roundtrip, ident, adj, jr_err

    # tiny batches: compile time dominates, so skip XLA's backend optimisations as well
    return _compile(jax.jit(run).lower(k1, k2), {"xla_backend_optimization_level": 0})(k1, k2)


def demo(args: argparse.Namespace) -> int:
    _enable_x64(not args.float32)
    import jax
    import jax.numpy as jnp

    import jaxpose as jp

    key = jax.random.PRNGKey(args.seed)
    dtype = jnp.float32 if args.float32 else jnp.float64
    print(f"jaxpose {jp.__version__} demo — JAX {jax.__version__} on {jax.default_backend()}, "
          f"{jnp.dtype(dtype).name}")

    # 1. Lie-group identities on a random batch of every group.
    print("\nLie groups: max errors over a batch of", args.batch, "random elements")
    print(f"{'group':6} {'Log(Exp(a))−a':>14} {'X·X⁻¹−I':>10} {'Adj identity':>13} "
          f"{'Jr·Jr⁻¹−I':>15}")
    for group in jp.GROUPS:
        k1, k2, key = jax.random.split(key, 3)
        errors = _group_checks(group, k1, k2, args.batch, dtype)
        print(f"{group.__name__:6} " + " ".join(
            f"{float(e):{w}.1e}" for e, w in zip(errors, (14, 10, 13, 15), strict=True)))

    # 2. Throughput of jitted, batched ops.
    n = args.throughput_batch
    phi = 0.5 * jax.random.normal(key, (n, 3), dtype)
    f1 = jax.jit(lambda p: jp.so3(p).exp().log().data)
    t0 = time.perf_counter()
    f1(phi).block_until_ready()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(5):
        f1(phi).block_until_ready()
    steady = (time.perf_counter() - t0) / 5
    print(f"\nLog(Exp(x)) on {n} so3 elements: {n / steady:.3g} op/s "
          f"(compile {compile_s:.2f} s)")

    # 3. Pose averaging with Adam on the manifold (tangent-space optax adapter).
    import optax

    @jax.jit  # one program (op by op, the set-up alone compiled ~90 tiny ones: ~2.5 s)
    def draw(key):
        k1, k2 = jax.random.split(key)
        truth = jp.SE3.random(k1, (), sigma=1.0, dtype=dtype)
        noise = 0.2 * jax.random.normal(k2, (args.poses, 6), dtype)
        return truth, truth.broadcast_to((args.poses,)).retract(noise)

    truth, samples = draw(key)

    def loss(x):
        return 0.5 * jnp.sum(samples.rminus(x.broadcast_to((args.poses,))) ** 2)

    opt = jp.manifold.optax_on_manifold(optax.adam(0.1))

    @jax.jit
    def step(x, state):
        value, grad = jp.manifold.value_and_grad(loss)(x)
        updates, state = opt.update(grad, state, x)
        return opt.apply_updates(x, updates), state, value

    x = jp.SE3.identity(dtype=dtype)
    state = opt.init(x)
    for i in range(args.steps):
        x, state, value = step(x, state)
        if i % max(1, args.steps // 5) == 0 or i == args.steps - 1:
            print(f"  Adam step {i:4d}  loss {float(value):.6e}")
    err = jax.jit(lambda x, truth: jnp.linalg.norm(x.rminus(truth)))(x, truth)
    print(f"Pose averaging over {args.poses} noisy SE3 samples: distance to the true pose "
          f"{float(err):.3e} (noise σ = 0.2, expected ≈ {0.2 * (6 / args.poses) ** 0.5:.3e})")

    # 4. Pose-graph optimisation on a generated sphere with loop closures.
    from .datasets import synthetic_pose_graph

    graph, truth = synthetic_pose_graph("SE3", n_poses=args.pgo_poses, noise=(0.01, 0.05),
                                        seed=args.seed)
    print(f"\nPose-graph optimisation: synthetic sphere, {graph.n_poses} poses, "
          f"{graph.n_edges} edges (odometry + loop closures), first pose fixed")
    _run_pgo(graph, kernel=None, solver="auto", max_steps=50, verbose=True, dtype=dtype)
    return 0


def _kernel(name: str | None, delta: float | None):
    """The robust kernel of ``--kernel NAME --kernel-delta DELTA`` (δ = 1 by default); a
    δ without a kernel is an error, not silently ignored."""
    if name is None or name == "none":
        if delta is not None:
            raise CLIError("--kernel-delta scales a robust kernel: give one with --kernel "
                           "(huber, cauchy, ...), or drop --kernel-delta")
        return None
    from . import optim

    kernels = {"huber": optim.Huber, "cauchy": optim.Cauchy, "pseudohuber": optim.PseudoHuber,
               "softlone": optim.SoftLOne, "arctan": optim.Arctan, "tukey": optim.Tukey,
               "gemanmcclure": optim.GemanMcClure, "welsch": optim.Welsch}
    if name not in kernels:
        raise CLIError(f"--kernel: expected one of {sorted(kernels)}, got {name!r}")
    return kernels[name](1.0 if delta is None else delta)


def _pose_graph_edge_costs(graph):
    """(m,) float64 ``0.5·rᵀΩr`` per edge at the initial poses, ``r = Log(Z⁻¹·Xi⁻¹·Xj)``
    (translation first), in numpy: checks the start point before anything is compiled."""
    import numpy as np

    from .lie._numpy import compose, inverse, rotvec_from_quat

    kind = graph.kind
    with np.errstate(all="ignore"):
        xi, xj = graph.poses[graph.edges[:, 0]], graph.poses[graph.edges[:, 1]]
        e = compose(kind, inverse(kind, xi), xj)
        e = compose(kind, inverse(kind, graph.measurements), e)
        if kind == "SE3":
            phi, t = rotvec_from_quat(e[:, 3:]), e[:, :3]
            th = np.linalg.norm(phi, axis=1, keepdims=True)
            small = th < 1e-6
            safe = np.where(small, 1.0, th)
            # V⁻¹ = I − K/2 + c·K², c = (1 − (θ/2)·cot(θ/2))/θ² (→ 1/12)
            c = np.where(small, 1 / 12, (1 - (safe / 2) / np.tan(safe / 2)) / safe**2)
            k_t = np.cross(phi, t)
            rho = t - 0.5 * k_t + c * np.cross(phi, k_t)
            r = np.concatenate([rho, phi], 1)
        else:
            th = np.arctan2(e[:, 3], e[:, 2])
            half = th / 2
            small = np.abs(half) < 1e-8
            a = np.where(small, 1.0, half / np.sin(np.where(small, 1.0, half)))  # (θ/2)/sin(θ/2)
            c, s = np.cos(-half), np.sin(-half)  # V⁻¹ = a·R(−θ/2)
            rho = a[:, None] * np.stack([c * e[:, 0] - s * e[:, 1], s * e[:, 0] + c * e[:, 1]], 1)
            r = np.concatenate([rho, th[:, None]], 1)
        return 0.5 * np.einsum("mi,mij,mj->m", r, graph.information, r)


def _check_initial_cost(costs, dtype, what, unit: str) -> None:
    """CLIError if the initial cost (per-item ``costs``) is not finite in ``dtype``;
    ``what(k)`` names item k in the message."""
    import numpy as np

    top = float(np.finfo(dtype).max)
    with np.errstate(all="ignore"):
        bad = np.flatnonzero(~(np.abs(costs) <= top))
        total = float(np.sum(costs, dtype=np.float64))
    name = np.dtype(dtype).name
    if bad.size:
        k = int(bad[0])
        raise CLIError(f"the initial cost of {unit} {what(k)} is not finite in {name} "
                       f"({costs[k]:.3g}): its values are too large")
    if not abs(total) <= top:
        raise CLIError(f"the initial cost ({total:.3g}) is not finite in {name}: values too "
                       "large")


def _compile(lowered, extra=None):
    """``lowered.compile()`` with :func:`jaxpose.compile_options` (and ``extra`` XLA
    options): a one-shot solve compiles 20–30 % faster on the CPU and runs within 5 %."""
    from ._compile import compile_options

    return lowered.compile(compiler_options={**compile_options(), **(extra or {})})


def _note_slow_blas(prog: str) -> None:
    """One line on stderr when the sparse factorisations ran on the reference BLAS for want
    of an optimised one (:func:`jaxpose.graph._cholmod.slow_blas`)."""
    from .graph import _cholmod

    why = _cholmod.slow_blas()
    if why is not None:
        print(f"{prog}: note: CHOLMOD ran on the {why} BLAS; large sparse factorisations "
              "are about 3x slower than with OpenBLAS (apt-get install libopenblas0, or "
              "JAXPOSE_BLAS=PATH of an LP64 BLAS)", file=sys.stderr)


FIX = "file"
"""Gauge of ``jaxpose pgo``: the file's FIX vertices held constant (pose 0 when it has
none), and the first pose of every other disconnected piece; written back with --out."""


def _run_pgo(graph, *, kernel, solver, max_steps, verbose, dtype, init="odometry"):
    """Solve a PoseGraph from its ``init`` start (in the compiled solve where
    ``start_in_solve``, else on the host), print the table and summary; returns
    (poses, solution)."""
    import jax

    from .graph import _pgo as pgo
    from .graph import default_stopping, solve

    stopping = default_stopping(max_steps, dtype)
    in_solve = pgo.start_in_solve(graph, init, FIX)
    if in_solve:
        problem = pgo.pose_graph_problem(graph, kernel=kernel, dtype=dtype, fix=FIX)
        run = jax.jit(lambda p: pgo.solve_from_start(
            p, init, linear_solver=solver, stopping=stopping, verbose=verbose))
    else:
        from .graph._init import initial_poses, pose_graph_cost

        t0 = time.perf_counter()
        start, method = initial_poses(graph, init, fix=FIX)
        init_s = time.perf_counter() - t0
        print(f"initialisation: {method} ({init_s:.3f} s), cost "
              f"{pose_graph_cost(graph, start):.6e}")
        problem = pgo.pose_graph_problem(graph, kernel=kernel, dtype=dtype, poses=start,
                                         fix=FIX)
        run = jax.jit(lambda p: (solve(p, linear_solver=solver, stopping=stopping,
                                       verbose=verbose), None))
    t0 = time.perf_counter()
    compiled = _compile(run.lower(problem))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol, chordal = compiled(problem)
    jax.block_until_ready(sol.cost)
    solve_s = time.perf_counter() - t0
    if in_solve:
        print(f"initialisation: {'chordal' if bool(chordal) else 'odometry'} (in the "
              "compiled solve)")
    print(f"initial cost {float(sol.initial_cost):.6e}  final cost {float(sol.cost):.6e}  "
          f"iterations {int(sol.iterations)}  status {sol.status_name}")
    print(f"time: solve {solve_s:.3f} s, compile {compile_s:.2f} s")
    _note_slow_blas("jaxpose pgo")
    return sol.variables["pose"].data, sol


def _run_pgo_gnc(graph, *, solver, max_steps, dtype, surrogate, init):
    """Outlier-robust solve (``--robust gnc``): graduated non-convexity with the odometry
    edges as known inliers; prints the summary and the rejected loop closures."""
    import jax
    import numpy as np

    from .graph import _pgo as pgo
    from .graph import default_stopping

    t0 = time.perf_counter()
    poses, sol = pgo.optimize_pose_graph(
        graph, robust="gnc", init=init, dtype=dtype, gnc_options={"surrogate": surrogate}, fix=FIX,
        linear_solver=solver, stopping=default_stopping(max_steps, dtype),
    )
    jax.block_until_ready(sol.cost)
    total_s = time.perf_counter() - t0
    w = np.asarray(sol.weights[0])
    loops = ~pgo.odometry_edges(graph)
    rejected = np.flatnonzero(loops & (w <= 0.5))
    print(f"GNC ({surrogate}): initial cost {float(sol.initial_cost):.6e}  weighted cost "
          f"{float(sol.cost):.6e}  robust cost {float(sol.robust_cost):.6e}  "
          f"GNC iterations {int(sol.iterations)}  LM iterations {int(sol.inner_iterations)}  "
          f"mu {float(sol.mu):.3g}  status {sol.status_name}")
    deleted, readmitted = int(sol.deletions), int(sol.readmissions)
    search = ", ".join(part for part in (
        f"{deleted} rejected" if deleted else "", f"{readmitted} re-admitted" if readmitted else "",
    ) if part)
    print(f"loop closures: {int(loops.sum()) - rejected.size} inliers, {rejected.size} "
          f"rejected" + (f" (local search after GNC: {search})" if search else "")
          + (f" (edges {', '.join(map(str, rejected[:10]))}"
             f"{', ...' if rejected.size > 10 else ''})" if rejected.size else ""))
    print(f"time: {total_s:.3f} s (including compilation)")
    _note_slow_blas("jaxpose pgo")
    return poses, sol


def pgo_command(args: argparse.Namespace) -> int:
    _enable_x64(not args.float32)
    import jax.numpy as jnp
    import numpy as np

    from .io import FormatError, read_g2o, write_g2o

    _check_output(args.out, "--out")
    _check_output(args.plot, "--plot")
    if args.plot:
        import importlib.util

        if importlib.util.find_spec("matplotlib") is None:
            raise CLIError("--plot needs matplotlib: pip install 'jaxpose[plot]'")
        from matplotlib.backend_bases import FigureCanvasBase

        ext = os.path.splitext(args.plot)[1].lower().lstrip(".")
        formats = FigureCanvasBase.get_supported_filetypes()
        if ext not in formats:  # none: matplotlib would write NAME.png, not NAME
            raise CLIError(f"--plot {args.plot}: expected one of the extensions "
                           f"{sorted(formats)}, got {ext or 'none'!r}")
    kernel = _kernel(args.kernel, args.kernel_delta)
    if args.robust == "gnc" and kernel is not None:
        raise CLIError("--robust gnc: GNC supplies its own robust loss; drop --kernel")
    if args.gnc_surrogate is not None and args.robust != "gnc":
        raise CLIError("--gnc-surrogate chooses the loss of --robust gnc: add --robust gnc, "
                       "or drop --gnc-surrogate")
    try:
        graph = read_g2o(args.file, information=args.information)
    except (FormatError, OSError) as err:
        print(f"jaxpose pgo: {err}", file=sys.stderr)
        return 1
    print(f"{args.file}: {graph.kind}, {graph.n_poses} poses, {graph.n_edges} edges")
    if graph.n_edges == 0:
        raise CLIError(f"{args.file}: the graph has no edges, nothing to optimise")
    if args.float32:
        _check_float32_range([graph.poses, graph.measurements, graph.information], args.file)
    dtype = jnp.float32 if args.float32 else jnp.float64
    ids = graph.vertex_ids[graph.edges]
    _check_initial_cost(_pose_graph_edge_costs(graph), dtype, lambda e: (
        f"{e} ({ids[e, 0]} -> {ids[e, 1]})"), "edge")
    if args.robust == "gnc":
        poses, sol = _run_pgo_gnc(graph, solver=args.solver, max_steps=args.max_steps,
                                  dtype=dtype, surrogate=args.gnc_surrogate or "tls",
                                  init=args.init)
    else:
        poses, sol = _run_pgo(graph, kernel=kernel, solver=args.solver,
                              max_steps=args.max_steps, verbose=not args.quiet, dtype=dtype,
                              init=args.init)
    poses = np.asarray(poses, np.float64)
    if not np.isfinite(poses).all():
        raise CLIError("the optimised poses are not finite; nothing written")
    if args.out:
        write_g2o(args.out, graph, poses=poses)
        print(f"wrote {args.out}")
    if args.plot:
        import jax

        from .graph import _pgo as pgo
        from .graph import marginals
        from .plot import plot_pose_graphs

        # pose marginals at the solution for the 2σ position ellipses
        problem = pgo.pose_graph_problem(graph, kernel=kernel, dtype=dtype, fix=FIX)
        if hasattr(sol, "weights"):  # GNC: the graph as weighted at the solution
            from .graph._robust import weighted_graph

            problem = weighted_graph(problem, sol.weights)
        cov = jax.jit(lambda p, v: marginals(p, v, "pose").covariances["pose"])(
            problem, sol.variables)
        cov = np.asarray(cov, np.float64)
        if not np.all(np.isfinite(cov)):
            print("jaxpose pgo: pose marginals are not finite; plotting without ellipses",
                  file=sys.stderr)
            cov = None
        plot_pose_graphs(args.plot, graph.kind, np.asarray(graph.poses), poses,
                         np.asarray(graph.edges), title=str(args.file), covariances=cov)
        print(f"wrote {args.plot}")
    return 0


def ba_command(args: argparse.Namespace) -> int:
    _enable_x64(not args.float32)
    import jax
    import jax.numpy as jnp
    import numpy as np

    from .graph import _ba as ba
    from .graph import default_stopping, solve
    from .io import BALProblem, FormatError, read_bal, write_bal
    from .io._bal import _bal_project_numpy
    from .optim import Nielsen

    _check_output(args.out, "--out")
    kernel = _kernel(args.kernel, args.kernel_delta)
    try:
        problem = read_bal(args.file)
    except (FormatError, OSError) as err:
        print(f"jaxpose ba: {err}", file=sys.stderr)
        return 1
    print(f"{args.file}: {problem.n_cameras} cameras, {problem.n_points} points, "
          f"{problem.n_observations} observations")
    if problem.n_observations == 0:
        raise CLIError(f"{args.file}: the problem has no observations, nothing to optimise")
    with np.errstate(all="ignore"):
        pred = _bal_project_numpy(problem.cameras, problem.points, problem.camera_index,
                           problem.point_index)
    bad = np.flatnonzero(~np.isfinite(pred - problem.observations).all(axis=1))
    if bad.size:
        k = int(bad[0])
        raise CLIError(
            f"{args.file}: observation {k} (camera {problem.camera_index[k]}, point "
            f"{problem.point_index[k]}) projects to a non-finite pixel {pred[k].tolist()} (the "
            "point is at depth 0: at the camera centre or in its focal plane; or the values "
            "overflow)")
    if args.float32:
        _check_float32_range([problem.cameras, problem.points, problem.observations], args.file)
    dtype = jnp.float32 if args.float32 else jnp.float64
    with np.errstate(all="ignore"):
        costs = 0.5 * np.sum((pred - problem.observations) ** 2, axis=1)
    _check_initial_cost(costs, dtype, lambda k: (
        f"{k} (camera {problem.camera_index[k]}, point {problem.point_index[k]})"),
        "observation")
    graph = ba.bundle_adjustment_problem(
        problem, kernel=kernel,
        eliminate=args.solver == "schur", fix_intrinsics=args.fix_intrinsics, dtype=dtype)
    stopping = default_stopping(args.max_steps, dtype)
    run = jax.jit(lambda g: solve(g, linear_solver=args.solver, damping="diagonal",
                                  strategy=Nielsen(1e-4), stopping=stopping,
                                  verbose=not args.quiet))
    t0 = time.perf_counter()
    compiled = _compile(run.lower(graph))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = jax.block_until_ready(compiled(graph))
    solve_s = time.perf_counter() - t0
    cams, points = ba.variables_to_bal(sol.variables)
    out = BALProblem(cams, points, problem.camera_index, problem.point_index,
                     problem.observations)
    print(f"initial cost {float(sol.initial_cost):.6e}  final cost {float(sol.cost):.6e}  "
          f"iterations {int(sol.iterations)}  status {sol.status_name}")
    print(f"reprojection RMSE {ba.reprojection_rmse(problem):.4g} -> "
          f"{ba.reprojection_rmse(out):.4g} px")
    print(f"time: solve {solve_s:.3f} s, compile {compile_s:.2f} s")
    _note_slow_blas("jaxpose ba")
    if not (np.isfinite(out.cameras).all() and np.isfinite(out.points).all()):
        raise CLIError("the optimised cameras or points are not finite; nothing written")
    if args.out:
        write_bal(args.out, out)
        print(f"wrote {args.out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxpose`` argument parser (subcommands demo, pgo, ba)."""
    parser = _Parser(prog="jaxpose", description=__doc__.splitlines()[0], epilog=EPILOG)
    debug_help = "on failure, print the traceback as well as the one-line message"
    parser.add_argument("--debug", action="store_true", help=debug_help)
    sub = parser.add_subparsers(dest="command")

    def add(name: str, **kw) -> argparse.ArgumentParser:
        p = sub.add_parser(name, epilog=EPILOG, **kw)
        # SUPPRESS: `jaxpose --debug pgo ...` is not reset by the subcommand's default
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                       help=debug_help)
        return p

    p = add("demo", help="run the built-in demo (no data needed)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch", type=_int_at_least(1), default=1000,
                   help="batch size for identity checks")
    p.add_argument("--throughput-batch", type=_int_at_least(1), default=100_000)
    p.add_argument("--poses", type=_int_at_least(1), default=200,
                   help="samples in the averaging problem")
    p.add_argument("--steps", type=_int_at_least(1), default=200, help="Adam steps")
    p.add_argument("--pgo-poses", type=_int_at_least(2), default=400,
                   help="poses in the synthetic graph")
    p.add_argument("--float32", action="store_true", help="run in float32 instead of float64")
    p.set_defaults(func=demo)

    q = _solve_command(add, "pgo", "optimise a g2o pose graph",
                       "input .g2o file (VERTEX_SE3:QUAT/EDGE_SE3:QUAT or SE2; its FIX vertices "
                       "are held constant, else the first pose)",
                       "graph to this .g2o file")
    q.add_argument("--plot", help="write a before/after plot with 2σ position ellipses of the "
                   "pose marginals (PNG; needs matplotlib; directory checked before solving)")
    _kernel_arguments(q, "kernel scale δ")
    q.add_argument("--robust", default=None, choices=["gnc"],
                   help="outlier-robust solve: graduated non-convexity (odometry edges are "
                        "known inliers; loop closures get inlier weights)")
    q.add_argument("--gnc-surrogate", default=None, choices=["tls", "gm"],
                   help="GNC loss: truncated least squares (default) or Geman-McClure; "
                        "needs --robust gnc")
    q.add_argument("--solver", default="auto", choices=["auto", "sparse", "pcg", "dense"])
    q.add_argument("--max-steps", type=_int_at_least(0), default=100)
    q.add_argument("--init", default="auto", choices=["auto", "chordal", "odometry"],
                   help="starting poses: chordal relaxation, the file's (odometry) poses, or "
                        "auto (chordal unless the file's poses have a lower cost)")
    q.add_argument("--information", default="strict", choices=["strict", "repair", "isotropic"],
                   help="non-positive-definite information matrices: error (strict), nearest "
                        "positive-definite (repair), SE-Sync trace weights for all (isotropic)")
    q.add_argument("--float32", action="store_true")
    q.add_argument("--quiet", action="store_true", help="no per-iteration table")
    q.set_defaults(func=pgo_command)

    b = _solve_command(add, "ba", "bundle-adjust a BAL problem", "input BAL problem file (.txt)",
                       "problem to this BAL file")
    _kernel_arguments(b, "kernel scale δ (pixels)")
    b.add_argument("--solver", default="schur", choices=["schur", "sparse", "pcg", "dense"])
    b.add_argument("--fix-intrinsics", action="store_true", help="hold f, k1, k2 constant")
    b.add_argument("--max-steps", type=_int_at_least(0), default=100)
    b.add_argument("--float32", action="store_true")
    b.add_argument("--quiet", action="store_true", help="no per-iteration table")
    b.set_defaults(func=ba_command)
    return parser


def _solve_command(
    add: Callable[..., argparse.ArgumentParser], name: str, summary: str, file_help: str,
    out_what: str,
) -> argparse.ArgumentParser:
    """A solving sub-command (``pgo``, ``ba``): its input ``file`` and ``--out``."""
    p = add(name, help=summary)
    p.add_argument("file", help=file_help)
    p.add_argument("--out", help=f"write the optimised {out_what} (its directory must exist; "
                   "checked before solving)")
    return p


def _kernel_arguments(p: argparse.ArgumentParser, delta_help: str) -> None:
    """``--kernel`` and ``--kernel-delta`` (shared by ``pgo`` and ``ba``)."""
    p.add_argument("--kernel", default=None, help="robust kernel: huber, cauchy, tukey, ...")
    p.add_argument("--kernel-delta", type=_positive_float, default=None,
                   help=f"{delta_help} (default 1; needs --kernel)")


def _message(err: BaseException) -> str:
    """One line for ``err``: an equinox runtime check's own message rather than JAX's
    wrapping; the exception type for anything that is not a known user-facing error."""
    from .io import FormatError

    text = str(err)
    m = re.search(r"EquinoxRuntimeError: (.+)", text)
    if m:
        return m.group(1).strip()
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    first = lines[0] if lines else ""
    if isinstance(err, (CLIError, FormatError, OSError)):
        return first
    hint = "" if isinstance(err, (ValueError, TypeError, ImportError)) else (
        " (unexpected: rerun with --debug for the traceback)")
    return f"{type(err).__name__}: {first}{hint}"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``jaxpose`` command line; returns the exit status (0 success, 1 failure, 2 bad
    command line). Failures print one line to stderr, no traceback unless ``--debug``.
    ``pgo`` run as the process's own command (``argv`` None) adds
    :data:`jaxpose._compile.WHOLE_LOOP_FLAGS` to ``XLA_FLAGS`` before JAX starts; called
    with ``argv`` from Python it leaves the environment alone, and JAX's float64 setting
    (which ``demo``, ``pgo`` and ``ba`` set for their run) is restored on return."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit_:  # --help (0) or a one-line usage error (2), already printed
        return exit_.code if isinstance(exit_.code, int) else 2
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    prog = f"jaxpose {args.command}"
    if args.command == "pgo" and argv is None:  # the process is the command: its XLA flags
        from ._compile import use_whole_loops

        use_whole_loops()
    # JAX logs a callback's exception (an equinox check) with its traceback before raising it
    callback_log = logging.getLogger("jax._src.callback")
    level = callback_log.level
    import jax

    x64 = jax.config.jax_enable_x64  # commands set their precision; a Python caller's returns
    if not args.debug:
        callback_log.setLevel(logging.CRITICAL)

    def show_warning(message, category, filename, lineno, file=None, line=None):
        print(f"{prog}: warning: {message}", file=sys.stderr)  # one line, no source excerpt

    try:
        with warnings.catch_warnings():
            if not args.debug:
                warnings.showwarning = show_warning
            return int(args.func(args))
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except Exception as err:
        if args.debug:
            traceback.print_exc()
        print(f"{prog}: {_message(err)}", file=sys.stderr)
        return 1
    finally:
        callback_log.setLevel(level)
        jax.config.update("jax_enable_x64", x64)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
