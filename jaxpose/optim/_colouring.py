"""Column colouring of a sparse Jacobian, compressed evaluation and the sparse normal matrix.

Given the structural pattern of J (m, n) (:func:`jaxpose.optim._sparsity.jacobian_pattern`),
rows are grouped into residual *blocks* (the d rows of one residual block share one column
set, so whitening and robust correctors, which mix the rows of a block, keep the
structure). Columns are coloured greedily (distance-1 colouring of the column intersection
graph: two columns conflict when one block touches both), so every block has at most one
column of each colour. One JVP per colour, with the seed Σ_{j of colour k} e_j, gives the
compressed Jacobian C = J·S (m, c) and J[i, col[i, k]] = C[i, k] recovers every entry.

The normal matrix H = JᵀJ is assembled from C. When the column intersection graph falls
apart into connected components (independent sub-problems, e.g. one pose per residual
block), H is block diagonal after a permutation and is kept as stacks of small dense
blocks, one stack per block size (:class:`BlockHessian`); its damped systems are solved
block by block. Otherwise, when H is large and sparse (banded problems, chains), it is
kept in CSR (:class:`~jaxpose.optim._sparse_hessian.SparseHessian`, solved by sparse
Cholesky); else H is dense, as on the dense path.
"""

from __future__ import annotations

import hashlib
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ._sparse_hessian import CSRStructure, SparseHessian, assemble, csr_structure

Array = jax.Array

MAX_BLOCK = 64  # largest independent column group solved as a dense block


def greedy_colouring(block_pattern: sp.csr_matrix) -> np.ndarray:
    """Colour of each column (n,) such that no block (row of ``block_pattern``) holds two
    columns of one colour (greedy, natural column order)."""
    p = sp.csr_matrix(block_pattern, dtype=np.int32)
    graph = (p.T @ p).tocsr()
    n = graph.shape[0]
    colour = np.full(n, -1, np.int64)
    for j in range(n):
        nb = graph.indices[graph.indptr[j]:graph.indptr[j + 1]]
        used = colour[nb]
        used = used[used >= 0]
        if used.size == 0:
            colour[j] = 0
            continue
        taken = np.zeros(used.max() + 2, bool)
        taken[used] = True
        colour[j] = int(np.argmin(taken))
    return colour


class Pattern:
    """Static (host) description of a coloured Jacobian: ``colmap`` (m, c) holds the
    column of colour k in row i's block (n where none); ``seeds`` (c, n) the JVP seeds;
    ``groups`` the column index stacks (nb, s) of H's diagonal blocks, or ``None``;
    ``csr`` H's sparse structure when H is kept in CSR, else ``None`` (neither: H is
    dense). Compared and hashed by content (it is a static pytree field)."""

    def __init__(self, m: int, n: int, colmap: np.ndarray, colour: np.ndarray,
                 groups: tuple[np.ndarray, ...] | None, csr: CSRStructure | None = None):
        self.m, self.n = m, n
        self.colmap = colmap
        self.colour = colour
        self.num_colours = int(colmap.shape[1])
        self.groups = groups
        self.csr = csr
        h = hashlib.sha1(np.asarray([m, n]).tobytes())
        h.update(colmap.tobytes())
        if groups is not None:
            for g in groups:
                h.update(g.tobytes())
        if csr is not None:
            h.update(b"csr")
            h.update(csr.indptr.tobytes())
            h.update(csr.indices.tobytes())
        self._key = h.hexdigest()
        self._plans: dict[str, Any] = {}

    def __hash__(self) -> int:
        return hash(self._key)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Pattern) and other._key == self._key

    def __repr__(self) -> str:
        if self.groups is not None:
            kind = "block-diagonal H " + ", ".join(
                f"{g.shape[0]}x{g.shape[1]}" for g in self.groups)
        elif self.csr is not None:
            kind = f"sparse H (CSR, nnz={self.csr.nnz})"
        else:
            kind = "dense H"
        return f"Pattern(m={self.m}, n={self.n}, colours={self.num_colours}, {kind})"

    @property
    def seeds(self) -> np.ndarray:
        """(num_colours, n) 0/1 seed matrix: row c selects the columns of colour c."""
        s = np.zeros((self.num_colours, self.n))
        s[self.colour, np.arange(self.n)] = 1.0
        return s

    def hessian_plan(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Per group: (rows, k, l, flat target) such that block entries accumulate
        C[rows, k]·C[rows, l] at ``target`` of the group's flattened (nb, s, s) stack."""
        if "h" in self._plans:
            return self._plans["h"]
        pos_group = np.full(self.n, -1)
        pos_block = np.zeros(self.n, np.int64)
        pos_local = np.zeros(self.n, np.int64)
        for gi, g in enumerate(self.groups or ()):
            nb, s = g.shape
            pos_group[g.reshape(-1)] = gi
            pos_block[g.reshape(-1)] = np.repeat(np.arange(nb), s)
            pos_local[g.reshape(-1)] = np.tile(np.arange(s), nb)
        c = self.num_colours
        rows, ks, ls = np.meshgrid(np.arange(self.m), np.arange(c), np.arange(c), indexing="ij")
        ca, cb = self.colmap[rows, ks], self.colmap[rows, ls]
        ok = (ca < self.n) & (cb < self.n)
        rows, ks, ls, ca, cb = rows[ok], ks[ok], ls[ok], ca[ok], cb[ok]
        plan = []
        for gi, g in enumerate(self.groups or ()):
            s = g.shape[1]
            sel = pos_group[ca] == gi
            tgt = (pos_block[ca[sel]] * s + pos_local[ca[sel]]) * s + pos_local[cb[sel]]
            plan.append((rows[sel], ks[sel], ls[sel], tgt))
        self._plans["h"] = plan
        return plan


def make_pattern(jac_pattern: sp.csr_matrix, block_of_row: np.ndarray) -> Pattern:
    """Colour the columns of an (m, n) pattern whose rows belong to residual blocks
    ``block_of_row`` (m,) and plan H's structure."""
    m, n = jac_pattern.shape
    nblocks = int(block_of_row.max()) + 1 if m else 0
    rows_to_blocks = sp.csr_matrix(
        (np.ones(m, np.int32), (block_of_row, np.arange(m))), shape=(nblocks, m))
    bp = (rows_to_blocks @ sp.csr_matrix(jac_pattern, dtype=np.int32)).tocsr()
    bp.data[:] = 1
    colour = greedy_colouring(bp)
    c = int(colour.max()) + 1 if n else 0
    bcolmap = np.full((nblocks, max(c, 1)), n, np.int64)
    coo = bp.tocoo()
    bcolmap[coo.row, colour[coo.col]] = coo.col
    colmap = bcolmap[block_of_row][:, : max(c, 1)]
    graph = (bp.T @ bp).tocsr()
    ncomp, label = connected_components(graph, directed=False)
    sizes = np.bincount(label, minlength=ncomp)
    groups, csr = None, None
    if ncomp > 1 and sizes.max() <= MAX_BLOCK:
        order = np.argsort(label, kind="stable")  # columns grouped by component
        by_size: dict[int, list[np.ndarray]] = {}
        starts = np.concatenate([[0], np.cumsum(np.bincount(label[order], minlength=ncomp))])
        for k in range(ncomp):
            cols = np.sort(order[starts[k]:starts[k + 1]])
            by_size.setdefault(cols.size, []).append(cols)
        groups = tuple(np.stack(v) for _, v in sorted(by_size.items()))
    else:
        csr = csr_structure(graph, colmap)
    return Pattern(m, n, colmap, colour, groups, csr)


class SparseJacobian(eqx.Module):
    """J (m, n) stored compressed: ``values`` (m, c) with J[i, colmap[i, k]] = values[i, k]."""

    values: Array
    pattern: Pattern = eqx.field(static=True)

    @property
    def shape(self) -> tuple[int, int]:
        """(m, n) of the Jacobian."""
        return (self.pattern.m, self.pattern.n)

    def dense(self) -> Array:
        """The (m, n) matrix."""
        p = self.pattern
        rows = np.broadcast_to(np.arange(p.m)[:, None], p.colmap.shape)
        out = jnp.zeros((p.m, p.n + 1), self.values.dtype)
        return out.at[rows, p.colmap].add(self.values)[:, : p.n]

    def matvec(self, v: Array) -> Array:
        """J v (m,)."""
        vp = jnp.concatenate([v, jnp.zeros((1,), v.dtype)])
        return jnp.sum(self.values * vp[self.pattern.colmap], axis=1)

    def rmatvec(self, r: Array) -> Array:
        """Jᵀ r (n,)."""
        p = self.pattern
        out = jnp.zeros((p.n + 1,), self.values.dtype)
        return out.at[p.colmap].add(self.values * r[:, None])[: p.n]

    def normal(self) -> Array | BlockHessian | SparseHessian:
        """H = JᵀJ: a :class:`BlockHessian` or a
        :class:`~jaxpose.optim._sparse_hessian.SparseHessian` when the pattern allows, else
        dense (n, n)."""
        p = self.pattern
        if p.csr is not None:
            return SparseHessian(assemble(self.values, p.csr), p)
        if p.groups is None:
            d = self.dense()
            return d.T @ d
        blocks = []
        for g, (rows, ka, kb, tgt) in zip(p.groups, p.hessian_plan()):
            nb, s = g.shape
            contrib = self.values[rows, ka] * self.values[rows, kb]
            flat = jnp.zeros((nb * s * s,), self.values.dtype).at[tgt].add(contrib)
            blocks.append(flat.reshape(nb, s, s))
        return BlockHessian(tuple(blocks), p)


class BlockHessian(eqx.Module):
    """Block-diagonal (after a column permutation) symmetric H: ``blocks[g]`` (nb, s, s)
    over the columns ``pattern.groups[g]`` (nb, s)."""

    blocks: tuple[Array, ...]
    pattern: Pattern = eqx.field(static=True)

    @property
    def shape(self) -> tuple[int, int]:
        """(n, n) of the Gauss-Newton matrix."""
        return (self.pattern.n, self.pattern.n)

    def _scatter(self, parts: list[Array]) -> Array:
        out = jnp.zeros((self.pattern.n,), parts[0].dtype)
        for g, p in zip(self.pattern.groups, parts):
            out = out.at[g.reshape(-1)].set(p.reshape(-1), unique_indices=True)  # a partition
        return out

    def __matmul__(self, v: Array) -> Array:
        return self._scatter([jnp.einsum("bij,bj->bi", b, v[g])
                              for b, g in zip(self.blocks, self.pattern.groups)])

    def diagonal(self) -> Array:
        """diag(H) (n,)."""
        return self._scatter([jnp.diagonal(b, axis1=1, axis2=2) for b in self.blocks])

    def dense(self) -> Array:
        """The (n, n) matrix."""
        n = self.pattern.n
        out = jnp.zeros((n, n), self.blocks[0].dtype)
        for b, g in zip(self.blocks, self.pattern.groups):
            out = out.at[g[:, :, None], g[:, None, :]].set(b)
        return out

    def solve(self, rhs: Array, diag_add: Array, method: str, rcond: float | None = None
              ) -> Array:
        """x with (H + diag(diag_add)) x = rhs, block by block (``method``: "cholesky",
        "lu" or "svd"); non-finite where a block is singular (Cholesky: not SPD)."""
        parts = []
        for b, g in zip(self.blocks, self.pattern.groups):
            a = b + jax.vmap(jnp.diag)(diag_add[g])
            r = rhs[g]
            if method == "cholesky":
                chol = jnp.linalg.cholesky(a)
                y = jax.scipy.linalg.solve_triangular(chol, r[..., None], lower=True)
                x = jax.scipy.linalg.solve_triangular(chol, y, lower=True, trans="T")[..., 0]
            elif method == "lu":
                x = jnp.linalg.solve(a, r[..., None])[..., 0]
            else:
                x = jnp.einsum("bij,bj->bi", jnp.linalg.pinv(a, rtol=rcond, hermitian=True), r)
            parts.append(x)
        return self._scatter(parts)


def as_dense(x: Any) -> Array:
    """The dense matrix of a :class:`SparseJacobian` / :class:`BlockHessian` /
    :class:`~jaxpose.optim._sparse_hessian.SparseHessian` (or ``x``)."""
    return x.dense() if isinstance(x, SparseJacobian | BlockHessian | SparseHessian) else x


def diagonal(h: Any) -> Array:
    """diag(H) of a dense, :class:`BlockHessian` or ``SparseHessian`` H."""
    return h.diagonal() if isinstance(h, BlockHessian | SparseHessian) else jnp.diagonal(h)


def identity_like(h: Any) -> Any:
    """The identity in the layout of H (dense, :class:`BlockHessian` or ``SparseHessian``):
    a loop carry of the right structure."""
    if isinstance(h, SparseHessian):
        return h.identity()
    if isinstance(h, BlockHessian):
        return BlockHessian(tuple(jnp.broadcast_to(jnp.eye(b.shape[-1], dtype=b.dtype),
                                                   b.shape) for b in h.blocks), h.pattern)
    return jnp.eye(h.shape[0], dtype=h.dtype)


def normal_equations(jac: Any, res: Array) -> tuple[Any, Array]:
    """(H, g) = (JᵀJ, Jᵀr) for a dense or :class:`SparseJacobian` J."""
    if isinstance(jac, SparseJacobian):
        return jac.normal(), jac.rmatvec(res)
    return jac.T @ jac, jac.T @ res


def _hessian_colouring(pattern: Pattern) -> np.ndarray:
    """Colour (n,) of H's columns such that no row of H holds two columns of one colour
    (H has JᵀJ's pattern: block-diagonal groups or ``pattern.csr``), cached on the
    pattern. Block-diagonal: the position inside the block."""
    if "hc" not in pattern._plans:
        if pattern.groups is not None:
            colour = np.zeros(pattern.n, np.int64)
            for g in pattern.groups:
                colour[g.reshape(-1)] = np.tile(np.arange(g.shape[1]), g.shape[0])
        else:
            csr = pattern.csr
            h = sp.csr_matrix((np.ones(csr.indices.size, np.int32), csr.indices, csr.indptr),
                              shape=(csr.n, csr.n))
            colour = greedy_colouring(h)
        pattern._plans["hc"] = colour
    return pattern._plans["hc"]


def compressed_hessian(grad: Any, x: Array, pattern: Pattern) -> BlockHessian | SparseHessian:
    """The Hessian of a scalar function with JᵀJ's sparsity, from one Hessian-vector
    product (``jax.jvp`` of its gradient ``grad: (n,) -> (n,)``) per colour of H's
    columns, in H's layout (:class:`BlockHessian` or ``SparseHessian``). Exact where the
    function's Hessian has that pattern (a sum of per-residual-block terms)."""
    colour = _hessian_colouring(pattern)
    seeds = np.zeros((int(colour.max()) + 1, pattern.n))
    seeds[colour, np.arange(pattern.n)] = 1.0
    hs = jax.vmap(lambda s: jax.jvp(grad, (x,), (s,))[1])(jnp.asarray(seeds, x.dtype))
    if pattern.groups is not None:  # blocks[b, i, j] = H[g[b, i], g[b, j]] = hs[j, g[b, i]]
        return BlockHessian(tuple(jnp.swapaxes(hs[: g.shape[1], g], 0, 1).mT
                                  for g in pattern.groups), pattern)
    csr = pattern.csr
    return SparseHessian(hs[colour[csr.indices], csr.row], pattern)


def compressed_jacobian(f: Any, x: Array, pattern: Pattern) -> tuple[Array, Array]:
    """(f(x), C = J·S (m, c)): one JVP of ``f: (n,) -> (m,)`` at ``x`` per colour."""
    seeds = jnp.asarray(pattern.seeds, x.dtype)
    return jax.vmap(lambda s: jax.jvp(f, (x,), (s,)), out_axes=(None, 1))(seeds)


__all__ = [
    "BlockHessian",
    "Pattern",
    "SparseJacobian",
    "as_dense",
    "compressed_hessian",
    "compressed_jacobian",
    "diagonal",
    "greedy_colouring",
    "identity_like",
    "make_pattern",
    "normal_equations",
]
