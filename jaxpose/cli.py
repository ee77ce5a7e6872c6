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
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence


def _enable_x64(enable: bool) -> None:
    import jax

    jax.config.update("jax_enable_x64", enable)


def _group_checks(group, k1, k2, batch, dtype):
    """Max errors of Log∘Exp, X·X⁻¹, the adjoint identity and Jr·Jr⁻¹ (jitted, one group)."""
    import jax
    import jax.numpy as jnp

    # tiny batches: compile time dominates, so skip XLA's backend optimisations
    @jax.jit(compiler_options={"xla_backend_optimization_level": 0})
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

    return run(k1, k2)


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

    k1, k2 = jax.random.split(key)
    truth = jp.SE3.random(k1, (), sigma=1.0, dtype=dtype)
    noise = 0.2 * jax.random.normal(k2, (args.poses, 6), dtype)
    samples = truth.broadcast_to((args.poses,)).retract(noise)

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
    err = jnp.linalg.norm(x.rminus(truth))
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


def _kernel(name: str | None, delta: float):
    if name is None or name == "none":
        return None
    from . import optim

    kernels = {"huber": optim.Huber, "cauchy": optim.Cauchy, "pseudohuber": optim.PseudoHuber,
               "softlone": optim.SoftLOne, "arctan": optim.Arctan, "tukey": optim.Tukey,
               "gemanmcclure": optim.GemanMcClure, "welsch": optim.Welsch}
    if name not in kernels:
        raise SystemExit(f"--kernel: expected one of {sorted(kernels)}, got {name!r}")
    return kernels[name](delta)


def _run_pgo(graph, *, kernel, solver, max_steps, verbose, dtype):
    """Solve a PoseGraph, print the table and summary; returns (poses, solution)."""
    import jax

    from .graph import pgo, solve

    problem = pgo.pose_graph_problem(graph, kernel=kernel, dtype=dtype)
    run = jax.jit(lambda p: solve(p, linear_solver=solver, max_steps=max_steps,
                                  verbose=verbose))
    t0 = time.perf_counter()
    compiled = run.lower(problem).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = compiled(problem)
    jax.block_until_ready(sol.cost)
    solve_s = time.perf_counter() - t0
    print(f"initial cost {float(sol.initial_cost):.6e}  final cost {float(sol.cost):.6e}  "
          f"iterations {int(sol.iterations)}  status {sol.status_name}")
    print(f"time: solve {solve_s:.3f} s, compile {compile_s:.2f} s")
    return sol.variables["pose"].data, sol


def _run_pgo_gnc(graph, *, kernel, solver, max_steps, dtype, surrogate):
    """Outlier-robust solve (``--robust gnc``): graduated non-convexity with the odometry
    edges as known inliers; prints the summary and the rejected loop closures."""
    import jax
    import numpy as np

    from .graph import pgo

    if kernel is not None:
        raise SystemExit("--robust gnc: GNC supplies its own robust loss; drop --kernel")
    t0 = time.perf_counter()
    poses, sol = pgo.optimize_pose_graph(
        graph, robust="gnc", dtype=dtype, gnc_options={"surrogate": surrogate},
        linear_solver=solver, max_steps=max_steps,
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
    print(f"loop closures: {int(loops.sum()) - rejected.size} inliers, {rejected.size} "
          f"rejected" + (f" (edges {', '.join(map(str, rejected[:10]))}"
                         f"{', ...' if rejected.size > 10 else ''})" if rejected.size else ""))
    print(f"time: {total_s:.3f} s (including compilation)")
    return poses, sol


def pgo_command(args: argparse.Namespace) -> int:
    _enable_x64(not args.float32)
    import jax.numpy as jnp
    import numpy as np

    from .io import FormatError, read_g2o, write_g2o

    try:
        graph = read_g2o(args.file)
    except (FormatError, OSError) as err:
        print(f"jaxpose pgo: {err}", file=sys.stderr)
        return 1
    print(f"{args.file}: {graph.kind}, {graph.n_poses} poses, {graph.n_edges} edges")
    dtype = jnp.float32 if args.float32 else jnp.float64
    if getattr(args, "robust", None) == "gnc":
        poses, _ = _run_pgo_gnc(graph, kernel=_kernel(args.kernel, args.kernel_delta),
                                solver=args.solver, max_steps=args.max_steps, dtype=dtype,
                                surrogate=args.gnc_surrogate)
    else:
        poses, _ = _run_pgo(graph, kernel=_kernel(args.kernel, args.kernel_delta),
                            solver=args.solver, max_steps=args.max_steps,
                            verbose=not args.quiet, dtype=dtype)
    poses = np.asarray(poses, np.float64)
    if args.out:
        write_g2o(args.out, graph, poses=poses)
        print(f"wrote {args.out}")
    if args.plot:
        from .plot import plot_pose_graphs

        plot_pose_graphs(args.plot, graph.kind, np.asarray(graph.poses), poses,
                         np.asarray(graph.edges), title=str(args.file))
        print(f"wrote {args.plot}")
    return 0


def ba_command(args: argparse.Namespace) -> int:
    _enable_x64(not args.float32)
    import jax
    import jax.numpy as jnp

    from .graph import ba, solve
    from .io import BALProblem, FormatError, read_bal, write_bal

    try:
        problem = read_bal(args.file)
    except (FormatError, OSError) as err:
        print(f"jaxpose ba: {err}", file=sys.stderr)
        return 1
    print(f"{args.file}: {problem.n_cameras} cameras, {problem.n_points} points, "
          f"{problem.n_observations} observations")
    dtype = jnp.float32 if args.float32 else jnp.float64
    graph = ba.bundle_adjustment_problem(
        problem, kernel=_kernel(args.kernel, args.kernel_delta),
        eliminate=args.solver == "schur", fix_intrinsics=args.fix_intrinsics, dtype=dtype)
    run = jax.jit(lambda g: solve(g, linear_solver=args.solver, damping="diagonal",
                                  lambda_init=1e-4, lambda_factor=None,
                                  max_steps=args.max_steps, verbose=not args.quiet))
    t0 = time.perf_counter()
    compiled = run.lower(graph).compile()
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
    if args.out:
        write_bal(args.out, out)
        print(f"wrote {args.out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jaxpose", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command")
    p = sub.add_parser("demo", help="run the built-in demo (no data needed)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch", type=int, default=1000, help="batch size for identity checks")
    p.add_argument("--throughput-batch", type=int, default=100_000)
    p.add_argument("--poses", type=int, default=200, help="samples in the averaging problem")
    p.add_argument("--steps", type=int, default=200, help="Adam steps")
    p.add_argument("--pgo-poses", type=int, default=400, help="poses in the synthetic graph")
    p.add_argument("--float32", action="store_true", help="run in float32 instead of float64")
    p.set_defaults(func=demo)

    q = sub.add_parser("pgo", help="optimise a g2o pose graph")
    q.add_argument("file", help="input .g2o file (VERTEX_SE3:QUAT/EDGE_SE3:QUAT or SE2)")
    q.add_argument("--out", help="write the optimised graph to this .g2o file")
    q.add_argument("--plot", help="write a before/after plot (PNG; needs matplotlib)")
    q.add_argument("--kernel", default=None, help="robust kernel: huber, cauchy, tukey, ...")
    q.add_argument("--kernel-delta", type=float, default=1.0, help="kernel scale δ")
    q.add_argument("--robust", default=None, choices=["gnc"],
                   help="outlier-robust solve: graduated non-convexity (odometry edges are "
                        "known inliers; loop closures get inlier weights)")
    q.add_argument("--gnc-surrogate", default="tls", choices=["tls", "gm"],
                   help="GNC loss: truncated least squares or Geman-McClure")
    q.add_argument("--solver", default="auto", choices=["auto", "sparse", "pcg", "dense"])
    q.add_argument("--max-steps", type=int, default=100)
    q.add_argument("--float32", action="store_true")
    q.add_argument("--quiet", action="store_true", help="no per-iteration table")
    q.set_defaults(func=pgo_command)

    b = sub.add_parser("ba", help="bundle-adjust a BAL problem")
    b.add_argument("file", help="input BAL problem file (.txt)")
    b.add_argument("--out", help="write the optimised problem to this BAL file")
    b.add_argument("--kernel", default=None, help="robust kernel: huber, cauchy, tukey, ...")
    b.add_argument("--kernel-delta", type=float, default=1.0, help="kernel scale δ (pixels)")
    b.add_argument("--solver", default="schur", choices=["schur", "sparse", "pcg", "dense"])
    b.add_argument("--fix-intrinsics", action="store_true", help="hold f, k1, k2 constant")
    b.add_argument("--max-steps", type=int, default=100)
    b.add_argument("--float32", action="store_true")
    b.add_argument("--quiet", action="store_true", help="no per-iteration table")
    b.set_defaults(func=ba_command)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
