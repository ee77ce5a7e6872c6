"""InvNet optimiser benchmark (the PyPose paper's optimiser table): jaxpose vs PyPose.

Problem (PyPose's pose-inversion example): learn X, a batch of B SE3 poses, such that
X · input = I for a batch of random SE3 ``input`` poses; residual ``Log(Xᵢ · inputᵢ)``
(B, 6), cost ``Σᵢ ‖Log(Xᵢ · inputᵢ)‖²``. ``input`` and the initial X are drawn once per
batch size (tangent N(0, I), like ``pp.randn_SE3``) and handed to both libraries.

Methods, batch B ∈ {1e1, 1e2, 1e3, 1e4}:

* jaxpose LM: ``jax.vmap`` of ``jaxpose.optim.least_squares`` (default LM: TrustRegion,
  Cholesky) over the B independent 6-dof problems, each with its own damping and
  stopping; one jitted call from the initial X to the end; stopped by PyPose's rule
  below (``StopOnPlateau``, per problem, no other tolerance);
* jaxpose LM joint: the problem as PyPose users write it, one
  ``jaxpose.optim.least_squares`` over the whole batch (one residual of shape (B, 6)),
  default settings (``jacobian="auto"``, which detects the block-diagonal Jacobian
  structure, evaluates it with 6 JVPs and solves the 6x6 blocks of JᵀJ), same stopping
  rule; compile time includes the sparsity analysis;
* jaxpose SGD / Adam: ``optax.sgd`` / ``optax.adam`` through
  ``jaxpose.lie.manifold.optax_on_manifold`` on the joint cost, a fixed number of steps in
  a jitted ``lax.fori_loop``;
* PyPose LM: ``pp.optim.LM`` (TrustRegion, Cholesky: its defaults) driven by
  ``StopOnPlateau(steps=10, patience=3, decreasing=1e-3)`` as in PyPose's own
  pose-inversion example; one model holding the B poses, so PyPose solves the joint dense
  (6B × 7B Jacobian) system. Batches whose dense system does not fit in the available
  memory are skipped with a printed reason (never faked).

"final error" is ``Σᵢ ‖Log(Xᵢ · inputᵢ)‖²`` of every method's final X, re-evaluated the
same way in float64 by jaxpose (so it measures the answer, not each library's own
float32 arithmetic), averaged over independent draws of the batch (``--draws``, default
5, and at least enough draws for 1000 problems: 100 draws of batch 10). In float32 both
LMs stop at 7-10x the round-off floor, and which one lands lower on a single draw of 10
problems changes from draw to draw; the per-draw comparison is printed. "own loss" is
the same sum as the library itself computes it (its dtype, its kernels). Two reference
rows per batch: the initial error, and the float32 floor (the exact inverse rounded to
the dtype; in float32 the residual's own rounding, ≈ eps·|t| per translation component,
keeps any solver a few times above it).
Times: steady-state seconds of a whole solve (best of repeats;
PyPose runs of over a second are timed once), jaxpose compile time separately. Ratios are
PyPose time / jaxpose time. Usage::

    python bench/optim.py [--quick] [--batches 10,100,1000,10000] [--dtype float32]
                          [--draws 5] [--threads N] [--sgd-steps 500] [--adam-steps 500]
                          [--out F.md]
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

if __package__ in (None, ""):  # run as a script: make `bench` and `jaxpose` importable
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


from bench._common import script_threads  # noqa: E402 - imports no jax

THREADS = script_threads(__name__)  # caps the BLAS/OpenMP pools before numpy/jax/torch load

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)  # float64 only for the error re-evaluation

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

import jaxpose.optim as jo  # noqa: E402
from bench._common import (  # noqa: E402
    Peer,
    Timing,
    apply_common,
    emit_report,
    environment,
    fmt_batch,
    fmt_ratio,
    fmt_seconds,
    import_peer,
    markdown_table,
    parser,
    time_jax,
    to_numpy,
    to_torch,
)
from jaxpose.lie import SE3, manifold  # noqa: E402

BAR = 5.0  # required PyPose-LM / jaxpose-LM time ratio (and error no worse)
DRAWS = 5  # independent draws of each batch (at least); final errors are their mean
MIN_PROBLEMS = 1000  # ... and enough draws that every mean covers ≥ this many problems
DRAW_SEED = 7919  # draw k uses seed DRAW_SEED·k (+ batch), draw 0 is the timed one


# ----------------------------------------------------------------------------------
# Problem
# ----------------------------------------------------------------------------------
def make_problem(batch: int, dtype: str, seed: int = 0) -> dict[str, np.ndarray]:
    """Random ``input`` and initial X as SE3 storage arrays (B, 7)."""
    rng = np.random.default_rng(seed + batch)
    inp = SE3.exp(jnp.asarray(rng.normal(size=(batch, 6)))).data
    x0 = SE3.exp(jnp.asarray(rng.normal(size=(batch, 6)))).data
    return {"input": np.asarray(inp, dtype), "x0": np.asarray(x0, dtype)}


@jax.jit
def _error64(x: jax.Array, inp: jax.Array) -> jax.Array:
    r = (SE3(x.astype(jnp.float64)) @ SE3(inp.astype(jnp.float64))).log().data
    return jnp.sum(r * r)


def final_error(x: Any, inp: Any) -> float:
    """Σ ‖Log(X·input)‖² in float64 (same evaluation for every method)."""
    return float(_error64(jnp.asarray(np.asarray(x)), jnp.asarray(np.asarray(inp))))


def residual(x: SE3, inp: SE3) -> jax.Array:
    return (x @ inp).log().data


# ----------------------------------------------------------------------------------
# jaxpose
# ----------------------------------------------------------------------------------
@dataclass
class Run:
    timing: Timing | None = None
    errors: list[float] | None = None  # final error of each draw of the batch
    iters: str = "—"
    note: str | None = None
    own: float | None = None

    @property
    def error(self) -> float | None:
        """Mean final error over the draws (one draw is mostly round-off in float32)."""
        return None if not self.errors else float(np.mean(self.errors))


# The stopping rule of PyPose's run below, per problem: StopOnPlateau(steps=10, patience=3,
# decreasing=1e-3) in PyPose's loss units (Σ‖r‖², twice this library's 0.5·Σ‖r‖² cost), and
# no other tolerance, so both libraries decide when to stop the same way.
LM_STOP: dict[str, Any] = {
    "stop": jo.StopOnPlateau(steps=10, patience=3, decreasing=0.5e-3),
    "gtol": 0.0, "xtol": 0.0, "cost_rtol": 0.0,
}


def _errors_of_draws(solve: Callable[..., Any], probs: Sequence[dict[str, np.ndarray]],
                     first: Any) -> list[float]:
    """Final errors of every draw: the timed draw's X, then one jitted solve per other
    draw (same shapes, one compile)."""
    jitted = jax.jit(solve)
    errors = [final_error(first, probs[0]["input"])]
    for p in probs[1:]:
        errors.append(final_error(jitted(jnp.asarray(p["x0"]), jnp.asarray(p["input"]))[0],
                                  p["input"]))
    return errors


def jaxpose_lm(probs: Sequence[dict[str, np.ndarray]], timing_kw: dict[str, Any]) -> Run:
    def solve(x0: jax.Array, inp: jax.Array) -> tuple[jax.Array, ...]:
        sol = jax.vmap(lambda x, a: jo.least_squares(residual, SE3(x), SE3(a), **LM_STOP))(
            x0, inp)
        return sol.params.data, sol.num_steps, sol.status, 2 * jnp.sum(sol.cost)

    x0, inp = jnp.asarray(probs[0]["x0"]), jnp.asarray(probs[0]["input"])
    timing, (x, steps, status, own) = time_jax(solve, x0, inp, **timing_kw)
    steps, status = np.asarray(steps), np.asarray(status)
    counts = np.bincount(status, minlength=4)
    note = None
    if counts[0] != status.size:
        note = f"statuses (conv/max/div/nonfinite) = {counts.tolist()}"
    return Run(timing, _errors_of_draws(solve, probs, x), f"{steps.min()}–{steps.max()}",
               note, float(own))


def jaxpose_joint(probs: Sequence[dict[str, np.ndarray]], timing_kw: dict[str, Any]) -> Run:
    """One least_squares over the whole batch (coloured Jacobian, block-diagonal solve)."""
    def solve(x0: jax.Array, inp: jax.Array) -> tuple[jax.Array, ...]:
        sol = jo.least_squares(residual, SE3(x0), SE3(inp), **LM_STOP)
        return sol.params.data, sol.num_steps, sol.status, 2 * sol.cost

    x0, inp = jnp.asarray(probs[0]["x0"]), jnp.asarray(probs[0]["input"])
    timing, (x, steps, status, own) = time_jax(solve, x0, inp, **timing_kw)
    note = None if int(status) == 0 else f"status {int(status)}"
    return Run(timing, _errors_of_draws(solve, probs, x), str(int(steps)), note, float(own))


def jaxpose_first_order(probs: Sequence[dict[str, np.ndarray]], opt: Any, steps: int,
                        timing_kw: dict[str, Any]) -> Run:
    mopt = manifold.optax_on_manifold(opt)

    def loss(x: SE3, inp: SE3) -> jax.Array:
        r = residual(x, inp)
        return 0.5 * jnp.sum(r * r)

    grad = manifold.grad(loss)

    def solve(x0: jax.Array, inp: jax.Array) -> tuple[jax.Array, jax.Array]:
        x, a = SE3(x0), SE3(inp)

        def body(_: int, carry: tuple[SE3, Any]) -> tuple[SE3, Any]:
            x, state = carry
            updates, state = mopt.update(grad(x, a), state, x)
            return mopt.apply_updates(x, updates), state

        x, _ = jax.lax.fori_loop(0, steps, body, (x, mopt.init(x)))
        return x.data, 2 * loss(x, a)

    x0, inp = jnp.asarray(probs[0]["x0"]), jnp.asarray(probs[0]["input"])
    timing, (x, own) = time_jax(solve, x0, inp, **timing_kw)
    return Run(timing, _errors_of_draws(solve, probs, x), str(steps), own=float(own))


# ----------------------------------------------------------------------------------
# PyPose
# ----------------------------------------------------------------------------------
def _available_bytes() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def pypose_dense_bytes(batch: int, itemsize: int) -> int:
    """Rough peak of PyPose's dense LM: a (6B × 7B) Jacobian and a (7B)² normal matrix,
    each held about twice (autograd output + working copy)."""
    m, n = 6 * batch, 7 * batch
    return 2 * itemsize * (m * n + n * n)


def pypose_lm(pp: Any, probs: Sequence[dict[str, np.ndarray]],
              timing_kw: dict[str, Any]) -> Run:
    """Timed on the first draw; the other draws are solved once each for their errors."""
    import torch

    batch = probs[0]["x0"].shape[0]
    itemsize = probs[0]["x0"].itemsize
    need = pypose_dense_bytes(batch, itemsize)
    avail = _available_bytes()
    if avail is not None and need > 0.8 * avail:
        return Run(note=f"skipped: PyPose's dense LM needs ≈{need / 2**30:.0f} GiB "
                        f"(6B×7B Jacobian + (7B)² normal matrix), "
                        f"{avail / 2**30:.0f} GiB available")

    class PoseInv(torch.nn.Module):
        def __init__(self, x0: Any) -> None:
            super().__init__()
            self.pose = pp.Parameter(pp.SE3(x0))

        def forward(self, inp: Any) -> Any:
            return (self.pose @ inp).Log().tensor()

    def solve(prob: dict[str, np.ndarray]) -> tuple[Any, int, float]:
        net = PoseInv(to_torch(prob["x0"]))
        inp = pp.SE3(to_torch(prob["input"]))
        opt = pp.optim.LM(net)
        sch = pp.optim.scheduler.StopOnPlateau(opt, steps=10, patience=3, decreasing=1e-3)
        sch.optimize(input=inp)
        with torch.no_grad():
            own = float(net(inp).square().sum())
        return to_numpy(net.pose.tensor()), sch.steps, own

    # one-off torch/PyPose start-up costs (excluded, like jaxpose's compile): a tiny solve
    solve(make_problem(2, str(probs[0]["x0"].dtype)))
    timing, (x, steps, own) = _time_eager(lambda: solve(probs[0]), timing_kw)
    errors = [final_error(x, probs[0]["input"])]
    errors += [final_error(solve(p)[0], p["input"]) for p in probs[1:]]
    return Run(timing, errors, str(steps), own=own)


def _time_eager(fn: Callable[[], Any], timing_kw: dict[str, Any]) -> tuple[Timing, Any]:
    """Best of repeated runs; a run over a second is timed once (no warm-up re-run:
    these runs are long enough that one-off costs are noise)."""
    import statistics

    repeats = timing_kw.get("repeats", 5)
    t0 = time.perf_counter()
    out = fn()
    samples = [time.perf_counter() - t0]
    if samples[0] < 1.0:  # short: the first run was the warm-up
        samples = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = fn()
            samples.append(time.perf_counter() - t0)
    return Timing(min(samples), statistics.median(samples), len(samples), 1), out


# ----------------------------------------------------------------------------------
# Driver and report
# ----------------------------------------------------------------------------------
def run(batches: Sequence[int], dtype: str, sgd_steps: int, adam_steps: int,
        timing_kw: dict[str, Any], log: Callable[[str], None],
        draws: int = 1) -> tuple[list[dict], Peer]:
    peer = import_peer("pypose")
    rows = []
    for b in batches:
        n_draws = max(draws, -(-MIN_PROBLEMS // b))
        probs = [make_problem(b, dtype, seed=DRAW_SEED * k) for k in range(n_draws)]

        def exact(p: dict[str, np.ndarray]) -> np.ndarray:
            return SE3(jnp.asarray(p["input"], jnp.float64)).inv().data.astype(dtype)

        cell: dict[str, Any] = {
            "batch": b,
            "initial": float(np.mean([final_error(p["x0"], p["input"]) for p in probs])),
            "floor": float(np.mean([final_error(exact(p), p["input"]) for p in probs])),
        }
        log(f"batch {b}: jaxpose LM")
        cell["jaxpose LM"] = jaxpose_lm(probs, timing_kw)
        log(f"batch {b}: jaxpose LM joint")
        cell["jaxpose LM joint"] = jaxpose_joint(probs, timing_kw)
        log(f"batch {b}: jaxpose SGD")
        cell["jaxpose SGD"] = jaxpose_first_order(probs, optax.sgd(0.1), sgd_steps,
                                                  timing_kw)
        log(f"batch {b}: jaxpose Adam")
        cell["jaxpose Adam"] = jaxpose_first_order(probs, optax.adam(0.01), adam_steps,
                                                   timing_kw)
        if peer.available:
            log(f"batch {b}: PyPose LM")
            try:
                cell["PyPose LM"] = pypose_lm(peer.module, probs, timing_kw)
            except Exception as err:  # noqa: BLE001 - reported, never faked
                cell["PyPose LM"] = Run(note=f"failed: {type(err).__name__}: {err}")
        else:
            cell["PyPose LM"] = Run(note=peer.label())
        rows.append(cell)
    return rows, peer


def report(rows: list[dict[str, Any]], peer: Peer, dtype: str, sgd_steps: int,
           adam_steps: int, draws: int = 1) -> tuple[str, str]:
    """The markdown report and its one-line verdict."""
    header = ["batch", "method", "final error", "own loss", "time", "compile", "iterations",
              "PyPose LM time / this"]
    table, notes = [], []
    verdicts: dict[str, list[str]] = {"met": [], "NOT met": [], "not checked": []}
    for cell in rows:
        ref = cell["PyPose LM"]
        b = fmt_batch(cell["batch"])
        table.append([b, "(initial X)", f"{cell['initial']:.2e}", "—", "—", "—", "—", "—"])
        table.append([b, f"({dtype} floor)", f"{cell['floor']:.2e}", "—", "—", "—", "—",
                      "—"])
        for name in ("jaxpose LM", "jaxpose LM joint", "jaxpose SGD", "jaxpose Adam",
                     "PyPose LM"):
            r: Run = cell[name]
            t = None if r.timing is None else r.timing.best
            comp = None if r.timing is None else r.timing.compile_s
            ratio = (fmt_ratio(ref.timing.best, t)
                     if ref.timing is not None and t and name != "PyPose LM" else "—")
            err = "—" if r.error is None else f"{r.error:.2e}"
            own = "—" if r.own is None else f"{r.own:.2e}"
            table.append([b, name, err, own, fmt_seconds(t),
                          fmt_seconds(comp) if comp is not None else "—", r.iters, ratio])
            if r.note:
                notes.append(f"- batch {fmt_batch(cell['batch'])}, {name}: {r.note}")
        joint = cell["jaxpose LM joint"]
        if ref.timing is not None and joint.timing is not None:
            notes.append(
                f"- batch {fmt_batch(cell['batch'])}: jaxpose LM joint (one coloured problem) "
                f"is {ref.timing.best / joint.timing.best:.0f}x faster than PyPose LM "
                f"(steady state; compile {joint.timing.compile_s:.2f} s), error "
                f"{joint.error:.2e} vs {ref.error:.2e}")
        lm = cell["jaxpose LM"]
        if ref.timing is not None and lm.timing is not None:
            speed = ref.timing.best / lm.timing.best
            cell_ok = speed >= BAR and lm.error <= ref.error
            verdicts["met" if cell_ok else "NOT met"].append(fmt_batch(cell["batch"]))
            pairs = list(zip(lm.errors, ref.errors, strict=True))
            lower = sum(a <= b for a, b in pairs)
            shown = ", ".join(f"{a:.2e}/{b:.2e}" for a, b in pairs[:5])
            notes.append(
                f"- batch {fmt_batch(cell['batch'])}: jaxpose LM is {speed:.0f}x faster, error "
                f"{lm.error:.2e} vs PyPose {ref.error:.2e} (mean of {len(pairs)} draws; "
                f"jaxpose lower or equal in {lower}/{len(pairs)}; first draws, "
                f"jaxpose/PyPose: {shown}) → bar {'met' if cell_ok else 'NOT met'}")
        else:
            verdicts["not checked"].append(fmt_batch(cell["batch"]))
            notes.append(f"- batch {fmt_batch(cell['batch'])}: no PyPose LM measurement, bar "
                         f"not checked")
    text = [
        f"# InvNet optimiser benchmark ({dtype})",
        "",
        f"Machine: {environment()}. Peer: {peer.label()}. Threads: "
        f"{THREADS if THREADS > 0 else 'library defaults'}.",
        f"SGD: lr 0.1, {sgd_steps} steps; Adam: lr 0.01, {adam_steps} steps (optax via "
        f"optax_on_manifold). Final error: Σ‖Log(X·input)‖² re-evaluated in float64, "
        f"mean over max({draws}, {MIN_PROBLEMS}/batch) independent draws of the batch (the "
        f"same draws for every method; in float32 one draw's final error is mostly "
        f"round-off); own loss, time, compile and iterations: the first draw; time: steady "
        f"state of a whole solve, compile separate.",
        "",
        markdown_table(header, table),
        "",
        *notes,
    ]
    parts = [f"{k} at batch {', '.join(v)}" for k, v in verdicts.items() if v]
    verdict = (f"bar (≥{BAR:.0f}x faster than PyPose LM, error no worse) "
               + "; ".join(parts) + (" (no PyPose LM measurement)" if verdicts["not checked"]
                                     else ""))
    return "\n".join(text), verdict


def main(argv: Sequence[str] | None = None) -> int:
    ap = parser(__doc__, quick="batches 1e1 and 1e2, fewer first-order steps and repeats")
    ap.add_argument("--batches", default=None, help="comma-separated batch sizes")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--sgd-steps", type=int, default=None)
    ap.add_argument("--adam-steps", type=int, default=None)
    ap.add_argument("--draws", type=int, default=None,
                    help=f"independent draws per batch for the final error (default {DRAWS}, "
                         f"--quick 2; at least {MIN_PROBLEMS}/batch); the first is also timed")
    args = ap.parse_args(argv)
    apply_common(args)
    global THREADS
    THREADS = args.threads
    if args.batches:
        batches = [int(float(b)) for b in args.batches.split(",")]
    else:
        batches = [10, 100] if args.quick else [10, 100, 1000, 10000]
    sgd = args.sgd_steps or (100 if args.quick else 500)
    adam = args.adam_steps or (100 if args.quick else 500)
    timing_kw = {"repeats": 3 if args.quick else 5, "max_time": 2.0 if args.quick else 10.0}
    log = lambda msg: print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr,
                            flush=True)
    draws = args.draws or (2 if args.quick else DRAWS)
    rows, peer = run(batches, args.dtype, sgd, adam, timing_kw, log, draws)
    text, verdict = report(rows, peer, args.dtype, sgd, adam, draws)
    text += f"\n\nResult: {verdict}"
    emit_report(text, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
