"""Compile time of differentiated solves, each measured cold in its own process.

What a user meets first in a notebook is the compilation of ``jax.jit(jax.grad(...))``
through a solver. Every entry runs in a fresh subprocess (no JIT cache, float64), twice:
with XLA's default options and with :func:`jaxpose.compile_options` (what a user can pass
to ``jax.jit(..., compiler_options=...)``), and reports the cold compile seconds of
``jit(f).lower(...).compile()`` (tracing, lowering and XLA) and the steady-state seconds
of one call. The budget is checked on the defaults. The lines of the optimised HLO
program (XLA defaults) are reported too: unlike the seconds, which move with the machine
a session is given (±15 % within minutes, 2x between machines), they are deterministic,
so they compare code changes across sessions (most of XLA:CPU's compile time is LLVM
code generation, which grows with the fused code).

Entries (issue 16's budget on an idle 2-core CPU in brackets):

* ``ls_solve``: ``least_squares`` on the InvNet problem (batch 100 SE3 poses, coloured
  Jacobian, LM), the solve alone;
* ``ls_grad``: ``grad`` of a scalar of its solution w.r.t. the 100 inputs [≤ 5 s];
* ``ls_hessian``: ``hessian`` w.r.t. a 6-vector perturbing every input [≤ 15 s];
* ``graph_solve``: ``graph.solve`` on parking-garage (1661 SE3 poses, 6275 edges), the
  solve alone;
* ``graph_grad``: ``grad`` w.r.t. the 6275 measurement perturbations [≤ 10 s].

optimistix's ``least_squares`` has no Lie-group parameters, so it cannot solve these. It is
the peer on a Euclidean problem both solve with the same method (Levenberg–Marquardt, a
dense Jacobian, implicit derivatives), a second table: ``curve_grad`` / ``curve_hessian``,
``grad`` and ``hessian`` of a fit of ``a·exp(−b·t) + c`` to 100 observations w.r.t. the
observations (a perturbation of them), each library in its own cold process, with the
largest relative difference of the two libraries' derivatives. Skipped, and said so,
where optimistix is not installed (``pip install optimistix``). Usage::

    python bench/compile.py [--quick] [--only ls_grad,graph_grad,curve_grad] [--out F.md]
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
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
    time_jax,
    worker_result,
)

BUDGET = {"ls_grad": 5.0, "ls_hessian": 15.0, "graph_grad": 10.0}
GARAGE = ROOT.parent / "shared" / "data" / "g2o" / "parking-garage.g2o"


# ----------------------------------------------------------------------------------
# entries (run inside a worker)
# ----------------------------------------------------------------------------------
def _invnet(batch: int) -> tuple[Callable[..., Any], tuple[Any, ...], Any]:
    import jax
    import jax.numpy as jnp

    import jaxpose.optim as jo
    from bench.optim import make_problem, residual
    from jaxpose.lie import SE3

    prob = make_problem(batch, "float64")
    x0, inp = SE3(jnp.asarray(prob["x0"])), SE3(jnp.asarray(prob["input"]))
    w = jax.random.normal(jax.random.PRNGKey(0), (batch, 7))

    def solve(inp_data: jax.Array) -> jax.Array:
        sol = jo.least_squares(residual, x0, SE3(inp_data))
        return jnp.sum(w * sol.params.data) + sol.cost

    return solve, (inp.data,), inp


def _garage() -> tuple[Callable[..., Any], Any]:
    import jax.numpy as jnp
    import numpy as np

    from jaxpose import graph as G
    from jaxpose.graph import between_residual
    from jaxpose.io import read_g2o
    from jaxpose.lie import SE3

    g = read_g2o(GARAGE)
    z, x0 = SE3(jnp.asarray(g.measurements)), SE3(jnp.asarray(g.poses))
    e = np.asarray(g.edges)
    w = jnp.asarray(np.random.default_rng(0).normal(size=x0.data.shape))

    def solve(noise: Any) -> Any:
        f = G.Factor(between_residual, [("pose", e[:, 0]), ("pose", e[:, 1])],
                     data=z.retract(noise), information=jnp.asarray(g.information))
        graph = G.FactorGraph([f], {"pose": x0}, fixed={"pose": np.array([0])})
        sol = G.solve(graph)
        return jnp.sum(w * sol.variables["pose"].data) + sol.cost

    return solve, jnp.zeros((e.shape[0], 6))


def _curve(impl: str) -> tuple[Callable[..., Any], Any, Any]:
    """(loss(obs), obs, a direction in obs): a weighted sum of the parameters of the
    least-squares fit of a·exp(−b·t) + c to ``obs`` (100 samples), by ``impl``."""
    import jax.numpy as jnp

    t = jnp.linspace(0.0, 4.0, 100)
    obs = 2.0 * jnp.exp(-1.3 * t) + 0.5 + 0.01 * jnp.sin(7.0 * t)
    y0, w = jnp.array([1.0, 1.0, 0.0]), jnp.array([1.0, 2.0, 3.0])

    def residual(y: Any, o: Any) -> Any:
        return y[0] * jnp.exp(-y[1] * t) + y[2] - o

    if impl == "optimistix":
        import optimistix as optx

        solver = optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12)

        def loss(o: Any) -> Any:
            sol = optx.least_squares(residual, solver, y0, args=o, max_steps=256)
            return jnp.sum(w * sol.value)
    else:
        import jaxpose.optim as jo

        def loss(o: Any) -> Any:
            return jnp.sum(w * jo.least_squares(residual, y0, o).params)

    return loss, obs, jnp.cos(t)


def _entry(name: str, quick: bool, impl: str = "jaxpose"
           ) -> tuple[Callable[..., Any], tuple[Any, ...]]:
    import jax
    import jax.numpy as jnp

    if name in PEER_ENTRIES:
        loss, obs, direction = _curve(impl)
        if name == "curve_grad":
            return jax.grad(loss), (obs,)
        return jax.hessian(lambda d: loss(obs + d * direction)), (jnp.zeros(()),)
    batch = 10 if quick else 100
    if name == "ls_solve":
        f, args, _ = _invnet(batch)
        return f, args
    if name == "ls_grad":
        f, args, _ = _invnet(batch)
        return jax.grad(f), args
    if name == "ls_hessian":
        f, _, inp = _invnet(batch)
        return jax.hessian(lambda d: f(inp.retract(jnp.broadcast_to(d, (batch, 6))).data)), (
            jnp.zeros(6),)
    if name == "graph_solve":
        f, noise = _garage()
        return f, (noise,)
    if name == "graph_grad":
        f, noise = _garage()
        return jax.grad(f), (noise,)
    raise ValueError(f"unknown entry {name!r}")


ENTRIES = ("ls_solve", "ls_grad", "ls_hessian", "graph_solve", "graph_grad")
PEER_ENTRIES = ("curve_grad", "curve_hessian")
PEERS = ("jaxpose", "optimistix")


def worker(name: str, quick: bool, options: bool, impl: str = "jaxpose") -> None:
    import jax
    import numpy as np

    import jaxpose

    jax.config.update("jax_enable_x64", True)
    f, args = _entry(name, quick, impl)
    opts = jaxpose.compile_options() if options else None
    timing, out = time_jax(f, *args, repeats=3, compiler_options=opts,
                           hlo_lines=not options)
    worker_result({"compile_s": timing.compile_s, "run_s": timing.median,
                   "hlo_lines": timing.hlo_lines,
                   "value": np.asarray(out, np.float64).ravel().tolist()})


def _peer_rows(only: Sequence[str], timeout: float) -> list[list[str]]:
    """The side-by-side table's rows: each entry of ``only`` in :data:`PEER_ENTRIES`, by
    jaxpose and optimistix, each in a cold process with XLA's defaults."""
    import importlib.util

    import numpy as np

    rows = []
    for name in (n for n in only if n in PEER_ENTRIES):
        if importlib.util.find_spec("optimistix") is None:
            rows.append([name, *["—"] * 7, "skipped: optimistix not installed"])
            continue
        outs = [spawn_worker([str(Path(__file__)), "--worker", name, "--impl", impl],
                             timeout=timeout, env={**os.environ, "XLA_FLAGS": ""})
                for impl in PEERS]
        failed = [f"{impl}: {o['failed']}" for impl, o in zip(PEERS, outs, strict=True)
                  if "failed" in o]
        if failed:
            rows.append([name, *["—"] * 7, "; ".join(failed)])
            continue
        ours, peer = outs
        a, b = np.asarray(ours["value"]), np.asarray(peer["value"])
        rel = float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))
        rows.append([name, fmt_seconds(ours["compile_s"]), fmt_seconds(peer["compile_s"]),
                     f"{ours['compile_s'] / peer['compile_s']:.2f}",
                     fmt_seconds(ours["run_s"]), fmt_seconds(peer["run_s"]),
                     f"{ours['run_s'] / peer['run_s']:.2f}",
                     f"{ours['hlo_lines']} / {peer['hlo_lines']}", f"{rel:.1e}"])
        print(f"{name}: jaxpose {ours['compile_s']:.2f} s, optimistix "
              f"{peer['compile_s']:.2f} s to compile; derivatives differ by {rel:.1e}",
              file=sys.stderr, flush=True)
    return rows


# ----------------------------------------------------------------------------------
# driver
# ----------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> int:
    ap = parser(__doc__, quick="batch 10 for the least-squares entries", threads=False,
                workers=True)
    ap.add_argument("--only", default=",".join(ENTRIES + PEER_ENTRIES),
                    help="comma-separated entries")
    ap.add_argument("--worker", default=None, help=argparse_hidden())
    ap.add_argument("--options", action="store_true", help=argparse_hidden())
    ap.add_argument("--impl", default="jaxpose", choices=PEERS, help=argparse_hidden())
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.worker, args.quick, args.options, args.impl)
        return 0
    only = args.only.split(",")
    unknown = [n for n in only if n not in ENTRIES + PEER_ENTRIES]
    if unknown:
        ap.error(f"--only: unknown entries {unknown}; choose from {ENTRIES + PEER_ENTRIES}")
    rows = []
    for name in (n for n in only if n in ENTRIES):
        if name.startswith("graph") and not Path(GARAGE).exists():
            rows.append([name, "—", "—", "—", "—", "—", "—", f"skipped: {GARAGE} missing"])
            continue
        flags = ["--quick"] if args.quick else []
        outs = [spawn_worker([str(Path(__file__)), "--worker", name, *flags, *extra],
                             timeout=args.timeout, env={**os.environ, "XLA_FLAGS": ""})
                for extra in ([], ["--options"])]
        failed = [o["failed"] for o in outs if "failed" in o]
        if failed:
            rows.append([name, "—", "—", "—", "—", "—", "—", failed[0]])
            continue
        default, opts = outs
        budget = BUDGET.get(name)
        verdict = "—" if budget is None else ("met" if default["compile_s"] <= budget else "over")
        rows.append([name, fmt_seconds(default["compile_s"]), fmt_seconds(default["run_s"]),
                     f"{default['hlo_lines']:,}".replace(",", " "),
                     fmt_seconds(opts["compile_s"]), fmt_seconds(opts["run_s"]),
                     "—" if budget is None else f"≤ {budget:g} s", verdict])
        print(f"{name}: compile {default['compile_s']:.2f} s, run {default['run_s']:.4f} s; "
              f"with compile_options {opts['compile_s']:.2f} s, {opts['run_s']:.4f} s",
              file=sys.stderr, flush=True)
    text = "\n".join([
        "# Compile time of differentiated solves (cold process per entry)",
        "",
        environment(),
        "",
        markdown_table(["entry", "cold compile", "steady run", "optimised HLO lines",
                        "cold compile, jaxpose.compile_options()", "steady run, same",
                        "budget (XLA defaults)", "verdict"], rows) if rows else "",
        "",
    ])
    peer_rows = _peer_rows(only, args.timeout)
    if peer_rows:
        text += "\n".join([
            "",
            "## Side by side with optimistix: a Euclidean fit (XLA defaults, cold process each)",
            "",
            markdown_table(["entry", "jaxpose compile", "optimistix compile", "ratio",
                            "jaxpose run", "optimistix run", "ratio",
                            "HLO lines jaxpose / optimistix",
                            "derivatives: max relative difference"], peer_rows),
            "",
        ])
    emit_report(text, args.out)
    return 0


def argparse_hidden() -> str:
    import argparse

    return argparse.SUPPRESS


if __name__ == "__main__":
    sys.exit(main())
