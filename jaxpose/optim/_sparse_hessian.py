"""The Gauss-Newton matrix H = JᵀJ in CSR form, assembled from a coloured Jacobian.

When the columns of a coloured Jacobian (:mod:`jaxpose.optim._colouring`) do not fall
apart into small independent groups but H is still sparse — banded smoothing problems,
chains, several long chains side by side — H is kept as CSR values ``data`` (nnz,) over a
static pattern computed once on the host (:class:`CSRStructure`): the pattern of BᵀB for
the residual-block pattern B, plus the whole diagonal. The values come from the
compressed Jacobian C (m, c) by one gather and one sorted segment sum (never an n×n
array): every row i adds C[i, k]·C[i, l] at the CSR position of (colmap[i, k],
colmap[i, l]).

H is kept sparse when n ≥ :data:`SPARSE_MIN_SIZE` and nnz(H)/n² ≤ :data:`SPARSE_MAX_FILL`;
smaller or fuller matrices are cheaper as a dense Cholesky. The damped system
(H + diag(a)) x = b is solved by the sparse direct solver of
:func:`jaxpose.graph._linear.solve_sparse_direct` (CHOLMOD on the host through a callback,
symbolic analysis cached per pattern) wrapped in ``jax.lax.custom_linear_solve``, so it
jits, vmaps (the callback runs once per problem) and differentiates (forward and reverse,
by the implicit rule of the linear solve; the callback itself is never differentiated).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

Array = jax.Array

SPARSE_MIN_SIZE = 128  # smallest n whose H is kept sparse (below: dense Cholesky is faster)
SPARSE_MAX_FILL = 0.05  # largest nnz(H) / n² kept sparse


class CSRStructure:
    """Static CSR pattern of H (n, n) and the gather plan from the compressed Jacobian.

    ``indices``/``indptr``: symmetric CSR (full pattern, sorted columns, int32); ``row``
    (nnz,) the row of each entry; ``diag`` (n,) the position of each diagonal entry;
    ``left``/``right``/``target`` (p,): H.data[target] += C.flat[left]·C.flat[right],
    sorted by target."""

    def __init__(self, graph: sp.csr_matrix, colmap: np.ndarray):
        n = graph.shape[0]
        h = (sp.csr_matrix(graph, dtype=np.int32) + sp.identity(n, np.int32, "csr")).tocsr()
        h.sort_indices()
        self.n = n
        self.indices = h.indices.astype(np.int32)
        self.indptr = h.indptr.astype(np.int32)
        self.row = np.repeat(np.arange(n, dtype=np.int32), np.diff(self.indptr))
        keys = self.row.astype(np.int64) * n + self.indices  # ascending
        self.diag = np.searchsorted(keys, np.arange(n, dtype=np.int64) * (n + 1))
        m, c = colmap.shape
        rows, ks, ls = np.meshgrid(np.arange(m), np.arange(c), np.arange(c), indexing="ij")
        ca, cb = colmap[rows, ks], colmap[rows, ls]
        ok = (ca < n) & (cb < n)
        target = np.searchsorted(keys, ca[ok] * n + cb[ok])
        order = np.argsort(target, kind="stable")
        self.target = target[order]
        self.left = (rows[ok] * c + ks[ok])[order]
        self.right = (rows[ok] * c + ls[ok])[order]

    @property
    def nnz(self) -> int:
        """Stored entries of H."""
        return int(self.indices.shape[0])


def csr_structure(graph: sp.csr_matrix, colmap: np.ndarray) -> CSRStructure | None:
    """The CSR plan of H when it is large and sparse enough (see the module docstring), else
    ``None``. ``graph`` (n, n) is the column intersection pattern BᵀB, ``colmap`` (m, c)."""
    n = graph.shape[0]
    if n < SPARSE_MIN_SIZE:
        return None
    nnz = graph.nnz + n - int(np.count_nonzero(graph.diagonal()))
    if nnz > SPARSE_MAX_FILL * n * n:
        return None
    return CSRStructure(graph, colmap)


def assemble(values: Array, csr: CSRStructure) -> Array:
    """H's CSR values (nnz,) from the compressed Jacobian ``values`` (m, c)."""
    flat = values.reshape(-1)
    contrib = flat[csr.left] * flat[csr.right]
    return jax.ops.segment_sum(contrib, jnp.asarray(csr.target), num_segments=csr.nnz,
                               indices_are_sorted=True)


def _matvec(csr: CSRStructure, data: Array, v: Array) -> Array:
    return jax.ops.segment_sum(data * v[csr.indices], jnp.asarray(csr.row),
                               num_segments=csr.n, indices_are_sorted=True)


class SparseHessian(eqx.Module):
    """Symmetric H (n, n) in CSR: ``data`` (nnz,) over ``pattern.csr``'s static pattern
    (``pattern``: the :class:`~jaxpose.optim._colouring.Pattern` of the coloured Jacobian)."""

    data: Array
    pattern: Any = eqx.field(static=True)

    @property
    def shape(self) -> tuple[int, int]:
        """(n, n) of the Gauss-Newton matrix."""
        return (self.pattern.n, self.pattern.n)

    def __matmul__(self, v: Array) -> Array:
        return _matvec(self.pattern.csr, self.data, v)

    def diagonal(self) -> Array:
        """diag(H) (n,)."""
        return self.data[self.pattern.csr.diag]

    def dense(self) -> Array:
        """The (n, n) matrix."""
        csr = self.pattern.csr
        return jnp.zeros((csr.n, csr.n), self.data.dtype).at[csr.row, csr.indices].set(self.data)

    def identity(self) -> SparseHessian:
        """The identity with this pattern."""
        csr = self.pattern.csr
        return SparseHessian(jnp.zeros_like(self.data).at[csr.diag].set(1.0), self.pattern)

    def solve(self, rhs: Array, diag_add: Array) -> Array:
        """x (n,) with (H + diag(diag_add)) x = rhs by sparse Cholesky (CHOLMOD on the
        host); NaN when the damped matrix is not positive definite."""
        from ..graph._linear import solve_sparse_spd  # graph imports optim: import late

        csr = self.pattern.csr
        data = self.data.at[csr.diag].add(diag_add)
        return solve_sparse_spd(data, jnp.asarray(csr.indices), jnp.asarray(csr.indptr), rhs)


__all__ = ["CSRStructure", "SPARSE_MAX_FILL", "SPARSE_MIN_SIZE", "SparseHessian", "assemble",
           "csr_structure"]
