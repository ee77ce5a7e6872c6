"""Throughput vs device count for batched workloads sharded with ``jaxpose.sharding``.

Workloads (each a batch of B independent items, float32):

* ``lie``: ``Log(Exp(a)·Exp(b))`` on B se3 pairs — ``shard_batch`` the inputs, then a
  plain ``jit`` (XLA partitions the element-wise work);
* ``lsq``: B noisy SE2 pose-graph loops of K poses, each solved by Levenberg–Marquardt
  (``vmap`` of ``jaxpose.optim.least_squares``) — ``shard_vmap``: every device runs its
  own while-loop until its problems are done;
* ``pgo``: B noisy SE2 pose graphs of equal structure (``jaxpose.datasets.
  synthetic_pose_graph``), each solved by the sparse factor-graph solver
  (``vmap`` of ``jaxpose.graph.solve``) — ``shard_vmap``;
* ``ekf``: an EKF (``jaxpose.filters.EKF``) over B kinematic-bicycle sequences of N range
  measurements — ``shard_vmap``.

Linear solver of ``lsq``/``pgo`` (``--linear-solver``): ``cg`` (default; conjugate
gradients, plain XLA code) or ``cholesky`` (LAPACK). With jaxlib 0.10.2 on CPU, the
batched LAPACK kernels split a large enough batch into chunks on XLA's intra-op thread
pool and *block a pool thread* until the chunks are done; when every pool thread (one
per core) runs such a kernel for a different simulated device at once, nothing is left
to run the chunks and the process deadlocks (observed here: 2 simulated devices on 2
cores, ``lsq`` with Cholesky, in ``jax::ParallelBatchMap``; ``--xla_cpu_multi_thread_
eigen=false`` does not help). GPUs/TPUs and one-device runs are not affected.

Each device count runs in its own subprocess with
``XLA_FLAGS=--xla_force_host_platform_device_count=D JAX_PLATFORMS=cpu`` (the flag must
be set before JAX starts). In that process the same batch is also run unsharded (one
device, the same jitted function without the mesh) and the largest difference between
the two results is reported: sharded runs must give the same numbers. Simulated CPU
devices share the machine's cores, so throughput can only grow up to the number of
cores; on a GPU/TPU host pass ``--real`` to use the real devices instead.

Usage::

    python bench/sharding.py [--quick] [--devices 1,2,4] [--workloads lie,lsq,ekf]
                             [--out FILE.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from typing import Any

if __package__ in (None, ""):  # run as a script: make `bench` and `jaxpose` importable
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np

from bench._common import emit_report, parser, spawn_worker, worker_result

WORKLOADS = ("lie", "lsq", "pgo", "ekf")
FULL = {"lie": 1 << 20, "lsq": 1024, "pgo": 256, "ekf": 512}
QUICK = {"lie": 1 << 14, "lsq": 32, "pgo": 16, "ekf": 32}
LOOP_POSES = 12
GRAPH_POSES = 16
EKF_STEPS = 50
LINEAR_SOLVERS = ("cg", "cholesky")


# ----------------------------------------------------------------------------------
# Workloads: make(B, key) -> (inputs, fn, how); fn(*inputs) -> pytree of arrays
# ----------------------------------------------------------------------------------
def lie_inputs(batch: int, dtype: Any = np.float32, seed: int = 0) -> tuple[Any, ...]:
    """Two (B, 6) twists, rotation angles up to ~2."""
    rng = np.random.default_rng(seed)
    return tuple(rng.normal(size=(batch, 6)).astype(dtype) for _ in range(2))


def lie_fn(a: Any, b: Any) -> Any:
    """``Log(Exp(a)·Exp(b))`` per row, (B, 6)."""
    import jaxpose as jp

    return (jp.se3(a).exp() @ jp.se3(b).exp()).log().data


def loop_inputs(
    batch: int, dtype: Any = np.float32, poses: int = LOOP_POSES, seed: int = 0
) -> tuple[Any, ...]:
    """B SE2 loops of ``poses`` poses on a circle: noisy odometry plus one loop closure
    (data ``(B, E, 4)`` measurements, E = poses) and a dead-reckoned initial guess
    ``(B, poses, 4)``."""
    rng = np.random.default_rng(seed)
    k = poses
    step = np.array([2 * np.pi * 5.0 / k, 0.0, 2 * np.pi / k])  # arc of a radius-5 circle
    twists = step + rng.normal(scale=[0.05, 0.05, 0.02], size=(batch, k, 3))
    meas = _se2_exp(twists)  # (B, E=k, 4): edge e: pose e -> pose (e+1) % k
    init = np.empty((batch, k, 4))
    init[:, 0] = [0.0, 0.0, 1.0, 0.0]
    for e in range(k - 1):  # dead reckoning along the odometry
        init[:, e + 1] = _se2_compose(init[:, e], meas[:, e])
    return meas.astype(dtype), init.astype(dtype)


def _se2_exp(v: np.ndarray) -> np.ndarray:
    th = v[..., 2]
    small = np.abs(th) < 1e-6
    s = np.where(small, 1.0, np.sin(th) / np.where(small, 1.0, th))
    c = np.where(small, 0.0, (1 - np.cos(th)) / np.where(small, 1.0, th))
    tx = s * v[..., 0] - c * v[..., 1]
    ty = c * v[..., 0] + s * v[..., 1]
    return np.stack([tx, ty, np.cos(th), np.sin(th)], -1)


def _se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ca, sa = a[..., 2], a[..., 3]
    tx = a[..., 0] + ca * b[..., 0] - sa * b[..., 1]
    ty = a[..., 1] + sa * b[..., 0] + ca * b[..., 1]
    return np.stack([tx, ty, ca * b[..., 2] - sa * b[..., 3], sa * b[..., 2] + ca * b[..., 3]], -1)


def loop_solve(meas: Any, init: Any, linear_solver: str = "cholesky") -> Any:
    """Solve one loop (``meas`` (E, 4), ``init`` (K, 4)) with LM: between residuals
    ``Log(Zₑ⁻¹·Xᵢ⁻¹·Xⱼ)`` and a stiff prior holding pose 0. Returns
    ``(poses (K, 4), cost, num_steps, status)``."""
    import jax.numpy as jnp

    import jaxpose as jp
    from jaxpose.optim import CG, Cholesky, LevenbergMarquardt, least_squares

    k = init.shape[0]
    i = jnp.arange(k)
    j = (i + 1) % k

    def residual(X: Any, Z: Any) -> Any:
        between = (Z.inv() @ X[i].inv() @ X[j]).log().data
        prior = 1e3 * X[0].log().data  # pose 0 at the identity
        return {"between": between, "prior": prior}

    lin = {"cg": CG(), "cholesky": Cholesky()}[_check_solver(linear_solver)]
    sol = least_squares(residual, jp.SE2(init), jp.SE2(meas), max_steps=50,
                        solver=LevenbergMarquardt(linear_solver=lin))
    return sol.params.data, sol.cost, sol.num_steps, sol.status


def _check_solver(name: str) -> str:
    if name not in LINEAR_SOLVERS:
        raise ValueError(f"linear_solver: expected one of {LINEAR_SOLVERS}, got {name!r}")
    return name


def graph_inputs(
    batch: int, dtype: Any = np.float32, poses: int = GRAPH_POSES, seed: int = 0
) -> tuple[Any, tuple[Any, ...]]:
    """B synthetic SE2 pose graphs of one structure (two laps of a circle with loop
    closures; seeds ``seed … seed+B−1``): the first graph's :class:`FactorGraph` (the
    structure) and the stacked initial poses ``(B, K, 4)`` and measurements
    ``(B, E, 4)``."""
    from jaxpose.datasets import synthetic_pose_graph
    from jaxpose.graph import _pgo as pgo

    graphs = [synthetic_pose_graph("SE2", n_poses=poses, noise=(0.02, 0.1), seed=seed + s)[0]
              for s in range(batch)]
    base = pgo.pose_graph_problem(graphs[0], dtype=dtype)
    init = np.stack([np.asarray(g.poses) for g in graphs]).astype(dtype)
    meas = np.stack([np.asarray(g.measurements) for g in graphs]).astype(dtype)
    return base, (init, meas)


def graph_solver(base: Any, linear_solver: str = "cholesky") -> Any:
    """``solve(init (K, 4), meas (E, 4)) → (poses (K, 4), cost, iterations, status)``:
    ``jaxpose.graph.solve`` on ``base`` with those values (``"cholesky"`` is the dense
    solver, ``"cg"`` the block-Jacobi PCG)."""
    import equinox as eqx

    from jaxpose.graph import default_stopping, solve
    from jaxpose.lie import SE2

    how = {"cg": "pcg", "cholesky": "dense"}[_check_solver(linear_solver)]

    def one(init: Any, meas: Any) -> Any:
        g = eqx.tree_at(lambda g: g.variables["pose"], base, SE2(init).normalize())
        g = eqx.tree_at(lambda g: g.factors[0].data, g, SE2(meas).normalize())
        sol = solve(g, linear_solver=how, stopping=default_stopping(50))
        return sol.variables["pose"].data, sol.cost, sol.iterations, sol.status

    return one


def ekf_inputs(
    batch: int, dtype: Any = np.float32, steps: int = EKF_STEPS, seed: int = 0
) -> tuple[Any, ...]:
    """B bicycle runs: controls ``(B, N, 2)`` and noisy range/speed measurements
    ``(B, N, 5)`` simulated from the model itself (numpy RNG, jaxpose rollout)."""
    import jax
    import jax.numpy as jnp

    from jaxpose.dynamics import Bicycle, rollout

    rng = np.random.default_rng(seed)
    us = np.stack(
        [rng.normal(0.0, 0.3, (batch, steps)), rng.normal(0.0, 0.05, (batch, steps))], -1
    ).astype(dtype)
    x0 = np.tile(np.array([5.0, 5.0, 0.3, 2.0], dtype), (batch, 1))
    _, ys = jax.jit(jax.vmap(lambda x, u: rollout(Bicycle(), x, u)))(x0, jnp.asarray(us))
    ys = np.asarray(ys) + rng.normal(0.0, 0.3, np.shape(ys))
    return us, ys.astype(dtype)


def ekf_fn(us: Any, ys: Any) -> Any:
    """EKF over one sequence → ``(estimates (N, 4), covariances (N, 4, 4))``."""
    import jax.numpy as jnp

    from jaxpose.dynamics import Bicycle
    from jaxpose.filters import EKF

    ekf = EKF(Bicycle(), Q=0.01 * jnp.eye(4), R=0.09 * jnp.eye(5))
    x0 = jnp.array([5.0, 5.0, 0.3, 2.0], us.dtype)
    res = ekf.run(x0, jnp.eye(4, dtype=us.dtype), ys, us)
    return res.x, res.P


def workload(
    name: str, batch: int, dtype: Any = np.float32, linear_solver: str = "cg"
) -> tuple[tuple[Any, ...], Any, str]:
    """Inputs, per-item function and how it is distributed: ``"data"`` (sharded inputs,
    plain ``jit`` of the batched function) or a :func:`~jaxpose.sharding.shard_vmap`
    method (``"partition"``: needed by ``least_squares``, whose lineax solves fail inside
    ``shard_map``; ``"shard_map"``: per-device programs without communication)."""
    if name == "lie":
        return lie_inputs(batch, dtype), lie_fn, "data"
    if name == "lsq":
        fn = lambda m, i: loop_solve(m, i, linear_solver)
        return loop_inputs(batch, dtype), fn, "partition"
    if name == "pgo":  # the PCG path uses lineax too
        base, inputs = graph_inputs(batch, dtype)
        how = "partition" if linear_solver == "cg" else "shard_map"
        return inputs, graph_solver(base, linear_solver), how
    if name == "ekf":
        return ekf_inputs(batch, dtype), ekf_fn, "shard_map"
    raise ValueError(f"workload: expected one of {WORKLOADS}, got {name!r}")


def sharded_and_plain(
    name: str, batch: int, devices: int | None = None, dtype: Any = np.float32,
    linear_solver: str = "cg",
) -> dict[str, Any]:
    """Build the workload and return the jitted plain (one device) and sharded callables
    with their inputs (used by the worker and by tests)."""
    import jax

    from jaxpose.sharding import batch_mesh, shard_batch, shard_vmap

    inputs, fn, how = workload(name, batch, dtype, linear_solver)
    mesh = batch_mesh(devices)
    dev0 = jax.devices()[0]
    plain_in = jax.device_put(inputs, dev0)
    sharded_in = shard_batch(inputs, mesh)
    if how == "data":
        plain = sharded = jax.jit(fn)  # already batched (element-wise over rows)
    else:
        plain = jax.jit(jax.vmap(fn))
        sharded = shard_vmap(fn, mesh, method=how)
    return dict(plain=plain, sharded=sharded, plain_in=plain_in, sharded_in=sharded_in,
                how=how, mesh=mesh)


def compare(a: Any, b: Any) -> tuple[float, int]:
    """``(largest |a − b| over the floating leaves, number of differing integer entries)``
    (iteration counts may differ by a step where float32 round-off meets a tolerance)."""
    import jax

    worst, mismatches = 0.0, 0
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        x, y = np.asarray(x), np.asarray(y)
        if x.shape != y.shape:
            raise ValueError(f"compare: shapes differ, {x.shape} vs {y.shape}")
        if np.issubdtype(x.dtype, np.floating):
            worst = max(worst, float(np.max(np.abs(x.astype(np.float64) - y), initial=0.0)))
        else:
            mismatches += int(np.sum(x != y))
    return worst, mismatches


# ----------------------------------------------------------------------------------
# Worker (one device count) and driver
# ----------------------------------------------------------------------------------
def _worker(args: argparse.Namespace) -> None:
    import jax

    from bench._common import time_jax

    timing_kw = (
        {"repeats": 3, "min_time": 0.01, "max_time": 1.0}
        if args.quick else {"repeats": 5, "min_time": 0.1, "max_time": 5.0}
    )
    sizes = QUICK if args.quick else FULL
    out: dict[str, Any] = {"devices": len(jax.devices()), "platform": jax.default_backend()}
    for name in args.workloads.split(","):
        batch = sizes[name]
        try:
            case = sharded_and_plain(name, batch, args.real_devices,
                                     linear_solver=args.linear_solver)
            t_plain, r_plain = time_jax(lambda *a: case["plain"](*a), *case["plain_in"],
                                        **timing_kw)
            t_shard, r_shard = time_jax(lambda *a: case["sharded"](*a), *case["sharded_in"],
                                        **timing_kw)
        except Exception as err:  # noqa: BLE001 - reported in the table, never hidden
            out[name] = {"error": f"{type(err).__name__}: {str(err)[:300]}"}
            continue
        leaf = jax.tree.leaves(r_shard)[0]
        diff, int_diff = compare(r_shard, r_plain)
        out[name] = dict(
            batch=batch, how=case["how"], plain_s=t_plain.best, sharded_s=t_shard.best,
            compile_s=t_shard.compile_s, diff=diff, int_diff=int_diff,
            spread=len(leaf.sharding.device_set),
        )
    worker_result(out)


def _spawn(devices: int, args: argparse.Namespace) -> dict[str, Any]:
    env = dict(os.environ)
    if not args.real:
        flags = env.get("XLA_FLAGS", "")
        env["XLA_FLAGS"] = (flags + f" --xla_force_host_platform_device_count={devices}").strip()
        env["JAX_PLATFORMS"] = "cpu"
    cmd = ["-m", "bench.sharding", "--worker", "--workloads", args.workloads,
           "--linear-solver", args.linear_solver]
    cmd += ["--quick"] if args.quick else []
    if args.real:
        cmd += ["--real-devices", str(devices)]
    out = spawn_worker(cmd, timeout=args.timeout, env=env, tail=5)
    if "failed" in out:
        return {"error": f"worker {out['failed']}"}
    return out


def report(results: dict[int, dict[str, Any]], args: argparse.Namespace,
           load: tuple[Any, Any]) -> str:
    from bench._common import environment, fmt_rate, fmt_seconds, markdown_table

    names = args.workloads.split(",")
    lines = [
        "# Sharding: throughput vs device count",
        "",
        f"{environment()}; {'real' if args.real else 'simulated CPU'} devices; "
        f"load average {load[0][0]:.1f} → {load[1][0]:.1f}; lsq/pgo linear solver "
        f"{args.linear_solver}" + (" (quick sizes)" if args.quick else ""),
        "",
    ]
    base = {n: (results.get(1, {}).get(n) or {}).get("sharded_s") for n in names}
    rows = []
    for d, res in sorted(results.items()):
        for n in names:
            r = res.get(n)
            if r is None or "error" in r:
                rows.append([n, d, "—", "—", "—", "—", "—", "—",
                             (r or res).get("error", "missing")])
                continue
            speed_1 = (f"{base[n] / r['sharded_s']:.2f}x" if base[n] else "—")
            rows.append([
                n, d, r["batch"], fmt_rate(r["batch"] / r["sharded_s"]),
                speed_1, f"{r['plain_s'] / r['sharded_s']:.2f}x",
                fmt_seconds(r["compile_s"]),
                f"{r['diff']:.1e}" + (f"; {r['int_diff']} counts differ" if r["int_diff"]
                                      else ""),
                f"{r['how']}, on {r['spread']} device(s)",
            ])
    lines.append(markdown_table(
        ["workload", "devices", "batch", "items/s", "vs 1 device", "vs unsharded (same run)",
         "compile", "max |sharded − unsharded|", "placement"], rows))
    top = max(results) if results else 0
    best = [f"{n} {base[n] / results[top][n]['sharded_s']:.2f}x"
            for n in names
            if base[n] and results.get(top, {}).get(n) and "sharded_s" in results[top][n]]
    lines += ["", f"Result: throughput at {top} devices vs 1: {', '.join(best) or '—'}"]
    lines += [
        "",
        "items/s: steady-state throughput of the sharded run (best of repeats). "
        "'vs 1 device': against the 1-device subprocess; 'vs unsharded': against the same "
        "batch on one device in the same subprocess. Simulated devices share the "
        f"machine's {os.cpu_count()} cores, and one device already uses all of them for "
        "large element-wise fusions and batched LAPACK calls, so simulated devices can "
        "only speed up work that runs on one thread per device (small sequential ops: "
        "filters, solver loops); 'partition' adds one all-reduce of the loop condition "
        "per while-loop iteration (the CG solver of lsq has an inner loop), 'shard_map' "
        "none.",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> str:
    ap = parser(__doc__, quick="small batches and few repeats", threads=False, workers=True)
    ap.add_argument("--devices", default="1,2,4", help="device counts to compare")
    ap.add_argument("--workloads", default=",".join(WORKLOADS))
    ap.add_argument("--linear-solver", default="cg", choices=LINEAR_SOLVERS,
                    help="linear solver of lsq/pgo (cholesky can deadlock on simulated CPU "
                    "devices with jaxlib 0.10.2: see the module docstring)")
    ap.add_argument("--real", action="store_true",
                    help="use the real devices of the default backend (GPU/TPU hosts)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--real-devices", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    bad = set(args.workloads.split(",")) - set(WORKLOADS)
    if bad:
        raise SystemExit(f"--workloads: unknown {sorted(bad)}; choose from {WORKLOADS}")
    if args.worker:
        _worker(args)
        return ""
    load0 = os.getloadavg()
    results: dict[int, dict[str, Any]] = {}
    for d in (int(x) for x in args.devices.split(",") if x):
        t0 = time.perf_counter()
        results[d] = _spawn(d, args)
        print(f"[{d} device(s)] {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    text = report(results, args, (load0, os.getloadavg()))
    return emit_report(text, args.out)


if __name__ == "__main__":
    main()
