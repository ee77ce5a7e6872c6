"""Linear solvers for the damped sparse normal equations (H + λD) δ = −g.

* :func:`solve_sparse_direct` — sparse supernodal Cholesky (CHOLMOD) on the host, called
  with ``jax.pure_callback``; works under ``jit`` and (sequentially) under ``vmap``. The
  symbolic analysis of each sparsity pattern is computed once and reused
  (:mod:`jaxpose.graph._cholmod`). If that module cannot load CHOLMOD, cholespy's public API
  is used (re-analyses every call: 2–4x slower), and without cholespy SciPy's SuperLU, which
  is much slower on large graphs (measured on sphere2500: 355 s for one SuperLU
  factorisation vs 1.0 s with cholespy on a loaded 2-core machine). Exact zeros are
  dropped from the pattern first when there are many (:func:`without_zeros`): factors
  with weight 0 then cost the factorisation nothing.
* :func:`solve_pcg` — matrix-free conjugate gradient with a block-Jacobi preconditioner,
  ``lineax.CG`` on lineax function operators (jit/vmap/differentiable, any backend).
* :func:`solve_dense` — assembles H densely and uses Cholesky (small problems; fully
  differentiable and vmappable); :func:`cholesky_solve_loops`, the same without LAPACK for
  the graph solver's loop when it compiles whole.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np

from .. import _small_linalg as small_linalg
from . import _cholmod as cholmod

Array = jax.Array


PRUNE_FRACTION = 0.02
"""Share of exactly-zero stored entries from which the host solvers drop them from the
pattern (:func:`without_zeros`). Every shared pose graph stores 0.02–1 % zeros (the held
pose's blocks), which leave the fill unchanged; a factor whose weight is 0 (a loop closure
that graduated non-convexity rejected, one a user switched off) stores a whole zero block
per slot pair, and dropping them removes its fill: sphere2500 with half its loop closures
replaced by random ones factorises in 340 ms with them, 8 ms without (GNC's last steps,
every random edge rejected). Compacting costs ~2 ms per 500 000 entries, counting the
zeros 0.06 ms."""


def without_zeros(data: np.ndarray, indices: np.ndarray, indptr: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The CSR matrix (data, indices, indptr) without its exactly-zero entries when they
    are at least :data:`PRUNE_FRACTION` of the stored ones, else unchanged. The matrix is
    the same, so is its factorisation's result; only the pattern the sparse analysis
    sees is smaller (a changed pattern is analysed once, then cached like any other)."""
    keep = data != 0
    kept = int(np.count_nonzero(keep))
    if data.size - kept < PRUNE_FRACTION * data.size:
        return data, indices, indptr
    before = np.zeros(data.size + 1, np.int64)
    np.cumsum(keep, out=before[1:])
    return data[keep], indices[keep], before[indptr].astype(indptr.dtype)


def _cholmod_solve(
    data: np.ndarray, indices: np.ndarray, indptr: np.ndarray, b: np.ndarray
) -> np.ndarray:
    data, indices, indptr = without_zeros(np.asarray(data), np.asarray(indices),
                                          np.asarray(indptr))
    if cholmod.available():
        return cholmod.solve(data, indices, indptr, b).astype(b.dtype)
    return _cholespy_solve(data, indices, indptr, b)


def _cholespy_solve(
    data: np.ndarray, indices: np.ndarray, indptr: np.ndarray, b: np.ndarray
) -> np.ndarray:
    try:
        from cholespy import CholeskySolverD, MatrixType
    except ImportError:
        return _scipy_solve(data, indices, indptr, b)
    n = b.shape[0]
    try:
        solver = CholeskySolverD(
            n,
            np.array(indptr, dtype=np.int32),
            np.array(indices, dtype=np.int32),
            np.array(data, dtype=np.float64),
            MatrixType.CSR,
        )
        x = np.zeros(n)
        solver.solve(np.array(b, dtype=np.float64), x)
    except (ValueError, RuntimeError):  # not positive definite: signal through NaN
        x = np.full(n, np.nan)
    return x.astype(b.dtype)


def _scipy_solve(
    data: np.ndarray, indices: np.ndarray, indptr: np.ndarray, b: np.ndarray
) -> np.ndarray:
    import scipy.sparse
    import scipy.sparse.linalg

    n = b.shape[0]
    # H is symmetric, so its CSR arrays read as CSC describe the same matrix.
    mat = scipy.sparse.csc_matrix(
        (np.asarray(data, np.float64), np.asarray(indices), np.asarray(indptr)), shape=(n, n)
    )
    try:
        lu = scipy.sparse.linalg.splu(
            mat, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True}
        )
        x = lu.solve(np.asarray(b, np.float64))
    except RuntimeError:  # exactly singular: report through non-finite values
        x = np.full(n, np.nan)
    return x.astype(b.dtype)


def solve_sparse_direct(data: Array, indices: Array, indptr: Array, b: Array) -> Array:
    """Solve A x = b for symmetric positive definite A in CSR (data, indices, indptr)."""
    out = jax.ShapeDtypeStruct(b.shape, b.dtype)
    return jax.pure_callback(
        _cholmod_solve, out, data, indices, indptr, b, vmap_method="sequential"
    )


def solve_sparse_spd(data: Array, indices: Array, indptr: Array, b: Array,
                     inner: Callable[[Callable[[Array], Array], Array], Array] | None = None
                     ) -> Array:
    """Solve A x = b, A symmetric positive definite in CSR, inside
    ``jax.lax.custom_linear_solve``: jit, vmap and derivatives of any order in ``data``
    and ``b`` (the implicit rule of the linear solve, with the CSR product as its
    operator; the inner solver is never differentiated). ``inner(matvec, rhs) -> x`` is
    the solver (default :func:`solve_sparse_direct`, CHOLMOD on the host; e.g.
    :func:`pcg_spd` on any backend)."""
    n = b.shape[0]
    rows = csr_rows(indptr, data.shape[0])

    def matvec(v: Array) -> Array:
        return jax.ops.segment_sum(data * v[indices], rows, num_segments=n,
                                   indices_are_sorted=True)

    def direct(_: object, rhs: Array) -> Array:
        return solve_sparse_direct(data, indices, indptr, rhs)

    return jax.lax.custom_linear_solve(matvec, b, direct if inner is None else inner,
                                       symmetric=True)


def pcg_spd(precond: Callable[[Array], Array], rtol: float, max_iters: int
            ) -> Callable[[Callable[[Array], Array], Array], Array]:
    """An ``inner`` solver for :func:`solve_sparse_spd`: :func:`solve_pcg` to ``rtol``
    with ``precond``; NaN where it has not reached ``rtol`` (relative residual, checked
    with one more product) within ``max_iters`` iterations, never a silently inexact
    answer."""

    def inner(matvec: Callable[[Array], Array], rhs: Array) -> Array:
        x, _ = solve_pcg(matvec, rhs, precond, rtol=rtol, max_iters=max_iters)
        residual = _two_norm(matvec(x) - rhs)
        ok = residual <= 10.0 * rtol * _two_norm(rhs)
        return jnp.where(ok, x, jnp.nan)

    return inner


def _two_norm(x: Array) -> Array:
    return jnp.sqrt(jnp.sum(x * x))


def solve_pcg(
    matvec: Callable[[Array], Array],
    b: Array,
    precond: Callable[[Array], Array],
    rtol: float | Array = 1e-8,
    max_iters: int = 1000,
) -> tuple[Array, Array]:
    """Preconditioned CG (``lineax.CG`` on ``lineax.FunctionLinearOperator``s) from x = 0.

    ``matvec`` and ``precond`` must be symmetric positive (semi-)definite. Stops when
    ‖r‖₂ ≤ rtol·‖b‖₂ (and lineax's matching test on the last update) or after
    ``max_iters`` iterations; ``rtol`` may be traced (inexact-Newton forcing terms).
    Returns (x, iterations)."""
    structure = jax.ShapeDtypeStruct(b.shape, b.dtype)
    psd = lx.positive_semidefinite_tag
    operator = lx.FunctionLinearOperator(matvec, structure, tags=psd)
    preconditioner = lx.FunctionLinearOperator(precond, structure, tags=psd)
    # floored at the smallest normal number: an atol of exactly 0 made lineax's test 0/0
    # (NaN, read as converged) on every zero entry of b, so CG stopped after one step
    atol = jnp.maximum(jnp.asarray(rtol, b.dtype) * jnp.linalg.norm(b),
                       jnp.finfo(b.dtype).tiny)
    solver = lx.CG(rtol=0.0, atol=atol, norm=_two_norm, max_steps=max_iters)
    sol = lx.linear_solve(operator, b, solver, options={"preconditioner": preconditioner},
                          throw=False)
    return sol.value, sol.stats["num_steps"]


def block_jacobi(blocks: tuple[Array, ...]) -> Callable[[Array], Array]:
    """Preconditioner from per-type diagonal blocks (n, d, d) of a symmetric positive-definite
    matrix (every diagonal block of one is too): applies their inverses (NaN for a block
    that is not positive definite)."""
    inverses = tuple(small_linalg.spd_inv(b) for b in blocks)

    def apply(v: Array) -> Array:
        out, start = [], 0
        for inv in inverses:
            n, d = inv.shape[0], inv.shape[1]
            seg = v[start : start + n * d].reshape(n, d)
            out.append(jnp.einsum("nij,nj->ni", inv, seg).reshape(-1))
            start += n * d
        return jnp.concatenate(out)

    return apply


SMALL_DENSE = 64
"""Largest system (tangent dimensions) the graph solver factorises with
:func:`cholesky_solve_loops` when loops compile whole
(:func:`jaxpose._compile.loops_compile_whole`). Its column steps take 1.4–2.6x LAPACK's
time (per solve in a compiled loop: N = 30 5.4 µs against 3.9, 54 14 against 8.6, 96 49
against 19); above this size that costs more than the ~10–20 µs of operation dispatch per
iteration that a loop compiled whole saves."""


def csr_rows(indptr: Array, nnz: int) -> Array:
    """(nnz,) row index of each stored entry of a CSR matrix with row pointers ``indptr``."""
    indptr = jnp.asarray(indptr)
    return jnp.repeat(jnp.arange(indptr.shape[0] - 1), jnp.diff(indptr),
                      total_repeat_length=nnz)


def dense_index(indices: Array, indptr: Array, size: int) -> Array:
    """(size·size,) position in the CSR values of each entry of the dense row-major matrix,
    ``nnz`` where the pattern holds none: :func:`densify` is then one gather (a scatter is a
    serial loop on XLA:CPU). Compute it once per pattern, outside a solver's loop."""
    nnz = indices.shape[0]
    rows = csr_rows(indptr, nnz)
    return (jnp.full((size * size,), nnz, jnp.int32)
            .at[rows * size + indices].set(jnp.arange(nnz, dtype=jnp.int32)))


def densify(data: Array, index: Array, size: int) -> Array:
    """The dense (size, size) matrix of CSR values ``data`` (:func:`dense_index`)."""
    padded = jnp.concatenate([data, jnp.zeros((1,), data.dtype)])
    return padded[index].reshape(size, size)


def solve_dense(data: Array, indices: Array, indptr: Array, b: Array) -> Array:
    """Densify the CSR matrix and solve with Cholesky (small problems only)."""
    n = b.shape[0]
    return cholesky_solve(densify(data, dense_index(indices, indptr, n), n), b)


def cholesky_solve(a: Array, b: Array) -> Array:
    """Solve ``a x = b`` for a symmetric positive-definite (n, n) ``a`` by LAPACK's (the
    backend's) Cholesky; NaN where ``a`` is not positive definite."""
    return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), b)


def cholesky_solve_loops(a: Array, b: Array, segment: int = 8) -> Array:
    """Solve ``a x = b`` for a symmetric positive-definite (n, n) ``a`` and b (n,) or
    (n, k) by Cholesky (Crout, one column per step) and a back substitution, each a
    ``fori_loop`` of vector operations: no LAPACK call, so a solver loop around it can
    compile into one XLA:CPU function (:func:`jaxpose._compile.loops_compile_whole`). The
    factorisation runs on ``a`` with ``bᵀ`` appended as last rows, so they end as
    ``(L⁻¹ b)ᵀ`` (the forward substitution, without a loop of its own). The columns go in
    segments of ``segment``: a segment's steps read only the rows and columns of L it can
    reach (about n³/3 multiply-adds in all, as LAPACK's, instead of n³). Not positive
    definite (a pivot ≤ 0): NaN, as JAX's LAPACK Cholesky. Small systems only
    (:data:`SMALL_DENSE`)."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    n = a.shape[0]
    rhs = b[:, None] if b.ndim == 1 else b  # (n, k)
    ab = jnp.concatenate([a, rhs.T.astype(a.dtype)], 0)  # (n + k, n)
    low = jnp.zeros_like(ab)
    for start in range(0, n, segment):
        stop = min(start + segment, n)
        row = jnp.arange(start, ab.shape[0])

        def column(j: Array, low: Array, start: int = start, stop: int = stop,
                   row: Array = row) -> Array:
            v = ab[start:, j] - low[start:, :stop] @ low[j, :stop]
            pivot = jax.lax.dynamic_index_in_dim(v, j - start, keepdims=False)
            col = jnp.where(row >= j, v / jnp.sqrt(pivot), 0.0)
            return jax.lax.dynamic_update_slice(low, col[:, None], (start, j))

        low = jax.lax.fori_loop(start, stop, column, low)
    y = low[n:]  # (k, n)

    def backward(k: Array, x: Array) -> Array:
        i = n - 1 - k
        return x.at[i].set((y[:, i] - low[:n, i] @ x) / low[i, i])

    x = jax.lax.fori_loop(0, n, backward, jnp.zeros_like(rhs))
    return x[:, 0] if b.ndim == 1 else x
