"""Banded least squares (1D smoothing chain): dense vs coloured Jacobian, dense vs sparse JᵀJ.

Problem: n scalar unknowns x, data residuals ``xᵢ + 0.2·sin(xᵢ) − yᵢ`` and smoothness
residuals ``2·dᵢ + 0.3·dᵢ³`` with dᵢ = xᵢ₊₁ − xᵢ (2n − 1 scalar residual blocks; J has 3
non-zeros per column, JᵀJ is tridiagonal). One ``jaxpose.optim.least_squares`` call
(default LM: TrustRegion, Cholesky) from x = 0, float64. Methods:

* dense: ``jacobian="fwd"`` (n JVPs per linearisation, dense n×n JᵀJ, dense Cholesky);
* coloured, dense H: ``jacobian="sparse"`` with the CSR form switched off (2 JVPs, dense
  JᵀJ and Cholesky): what colouring alone buys;
* coloured, sparse H: ``jacobian="sparse"`` (the default ``"auto"`` picks it here): JᵀJ
  in CSR assembled from the compressed Jacobian, sparse Cholesky (CHOLMOD on the host).

Times: steady-state seconds of a whole solve (best of repeats) and compile seconds (trace,
sparsity analysis and XLA compile) separately. Every method must reach the same answer
(max |x − x_dense| is printed). Usage::

    python bench/sparse_chain.py [--quick] [--sizes 600,1500,3000] [--dense-max 3000]
                                 [--out F.md]
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

if __package__ in (None, ""):  # run as a script: make `bench` and `jaxpose` importable
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bench._common import DEFAULT_THREADS, early_threads  # noqa: E402 - imports no jax

THREADS = early_threads() if __name__ == "__main__" else DEFAULT_THREADS

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxpose.optim as jo  # noqa: E402
from bench._common import (  # noqa: E402
    apply_common,
    emit_report,
    environment,
    fmt_ratio,
    fmt_seconds,
    markdown_table,
    parser,
    time_jax,
)
from jaxpose.optim import _problem  # noqa: E402
from jaxpose.optim import _sparse_hessian as sparse_hessian  # noqa: E402

SIZES = (600, 1500, 3000)
QUICK_SIZES = (600, 1500)


def chain(x: jax.Array, y: jax.Array) -> jax.Array:
    """Data and smoothness residuals of the chain, as scalar blocks (2n − 1, 1)."""
    data = x + 0.2 * jnp.sin(x) - y
    d = x[1:] - x[:-1]
    return jnp.concatenate([data, 2.0 * d + 0.3 * d**3])[:, None]


def _solve(mode: str):
    # a new function object per method: least_squares' trace cache (keyed by the
    # residual function) must not hand one method's program to the next
    def fn(x: jax.Array, y: jax.Array) -> jax.Array:
        return chain(x, y)

    def run(x0: jax.Array, y: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        sol = jo.least_squares(fn, x0, y, jacobian=mode)
        return sol.params, sol.num_steps, sol.cost

    return run


def _time(mode: str, csr: bool, x0: jax.Array, y: jax.Array):
    saved = sparse_hessian.SPARSE_MIN_SIZE
    _problem._PATTERNS.clear()  # the pattern (and its H form) is cached per program
    if not csr:
        sparse_hessian.SPARSE_MIN_SIZE = 1 << 62
    try:
        return time_jax(_solve(mode), x0, y, repeats=5, max_time=20.0)
    finally:
        sparse_hessian.SPARSE_MIN_SIZE = saved
        _problem._PATTERNS.clear()


def run(sizes: Sequence[int], dense_max: int = 3000) -> list[list[str]]:
    rows = []
    for n in sizes:
        y = jnp.asarray(np.cumsum(np.random.default_rng(n).normal(size=n)) * 0.3)
        x0 = jnp.zeros(n)
        methods = [("coloured, sparse H", "sparse", True)]
        if n <= dense_max:
            methods = [("dense (jacfwd, dense H)", "fwd", False),
                       ("coloured, dense H", "sparse", False)] + methods
        else:
            print(f"n = {n}: dense methods skipped (--dense-max {dense_max})", flush=True)
        results = []
        for label, mode, csr in methods:
            t, (x, s, _) = _time(mode, csr, x0, y)
            results.append((label, t, x, s))
        t_ref, x_ref = results[0][1], results[0][2]
        for label, t, x, s in results:
            err = float(jnp.max(jnp.abs(x - x_ref)))
            rows.append([str(n), label, str(int(s)), fmt_seconds(t.best), fmt_seconds(t.compile_s),
                         fmt_ratio(t_ref.best, t.best) if n <= dense_max else "—",
                         f"{err:.1e}" if n <= dense_max else "—"])
            print(" | ".join(rows[-1]), flush=True)
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    ap = parser(__doc__, quick="n = 600, 1500")
    ap.add_argument("--sizes", default=None, help="comma-separated n")
    ap.add_argument("--dense-max", type=int, default=3000,
                    help="largest n timed with the dense methods (O(n³) per step)")
    args = ap.parse_args(argv)
    apply_common(args)
    sizes = (tuple(int(s) for s in args.sizes.split(",")) if args.sizes
             else QUICK_SIZES if args.quick else SIZES)
    rows = run(sizes, args.dense_max)
    text = "\n".join([
        "## Banded least squares (smoothing chain): dense vs coloured, dense vs sparse JᵀJ",
        "",
        f"{environment()}; threads {args.threads}; float64; one LM solve from x = 0.",
        "",
        markdown_table(["n", "method", "steps", "solve", "compile", "speed-up vs dense",
                        "max |x − x_dense|"], rows),
    ])
    emit_report(text, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
