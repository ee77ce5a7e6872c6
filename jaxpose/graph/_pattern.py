"""Block-sparse symmetric matrices: the host-side pattern and the jitted value assembly.

A matrix over variables of several types (type t: ``counts[t]`` variables of dimension
``dims[t]``; row/column layout: types in the given order, variable i of type t owning the
contiguous slice ``offsets[t] + i·dims[t]``) is stored as dense blocks, one array per
*class* = ordered pair of types (ta, tb) with shape ``(n_blocks, dims[ta], dims[tb])``.
Within a class, blocks are sorted by (row variable, column variable). Every diagonal block
exists. The scalar CSR form (sorted column indices, full symmetric pattern) is a fixed
gather ``perm`` from the concatenated flattened class arrays, computed once here with numpy,
so each evaluation is: scatter-add block products into the class arrays, then one gather.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array


class BlockPattern(eqx.Module):
    """Pattern of a symmetric block-sparse matrix (see the module docstring).

    ``classes[c] = (ta, tb, n_blocks)``; ``class_of[(ta, tb)] = c`` via :meth:`class_id`."""

    dims: tuple[int, ...] = eqx.field(static=True)
    classes: tuple[tuple[int, int, int], ...] = eqx.field(static=True)
    size: int = eqx.field(static=True)
    nnz: int = eqx.field(static=True)
    indices: Array  # (nnz,) CSR column indices
    indptr: Array  # (size + 1,)
    diag_pos: Array  # (size,) CSR positions of the diagonal
    perm: Array  # (nnz,) CSR entry → position in the concatenated class arrays
    block_rows: tuple[Array, ...]  # per class (n_blocks,): row variable (within its type)
    block_cols: tuple[Array, ...]  # per class (n_blocks,): column variable

    def class_id(self, ta: int, tb: int) -> int:
        for c, (a, b, _) in enumerate(self.classes):
            if (a, b) == (ta, tb):
                return c
        raise KeyError((ta, tb))

    def zeros(self, dtype) -> list[Array]:
        """Empty class arrays."""
        return [jnp.zeros((n, self.dims[a], self.dims[b]), dtype) for a, b, n in self.classes]

    def csr(self, blocks: Sequence[Array]) -> Array:
        """Class arrays → CSR values (nnz,)."""
        return jnp.concatenate([b.reshape(-1) for b in blocks])[self.perm]

    def without_fixed(self, blocks: Sequence[Array], free: Sequence[Array]) -> list[Array]:
        """Class arrays with every block of a fixed variable (row or column) zeroed;
        ``free[t]`` (counts[t],) is 1 for the free variables of type t, 0 for fixed ones."""
        return [b * (free[a][r] * free[t][c]).astype(b.dtype)[:, None, None]
                for b, (a, t, _), r, c in zip(blocks, self.classes, self.block_rows,
                                              self.block_cols, strict=True)]


def build_pattern(
    counts: Sequence[int],
    dims: Sequence[int],
    pairs: Sequence[tuple[int, np.ndarray, int, np.ndarray]],
) -> tuple[BlockPattern, list[tuple[int, np.ndarray]]]:
    """Pattern holding blocks (a, b) for every ``(ta, idx_a, tb, idx_b)`` in ``pairs``.

    Returns the pattern and, per pair, ``(class id, block index within the class)`` (m,).
    The transposed blocks (b, a) and all diagonal blocks are included as well."""
    counts = [int(c) for c in counts]
    dims = [int(d) for d in dims]
    n_types = len(counts)
    base = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    n_vars = int(base[-1])
    var_type = np.repeat(np.arange(n_types), counts)
    var_dim = np.asarray(dims, np.int64)[var_type]
    var_off = np.concatenate([[0], np.cumsum(var_dim)]).astype(np.int64)
    size = int(var_off[-1])

    glob = [(base[ta] + np.asarray(ia, np.int64), base[tb] + np.asarray(ib, np.int64))
            for ta, ia, tb, ib in pairs]
    diag = np.arange(n_vars, dtype=np.int64)
    ga = np.concatenate([diag] + [a for a, _ in glob] + [b for _, b in glob])
    gb = np.concatenate([diag] + [b for _, b in glob] + [a for a, _ in glob])
    keys = np.unique(ga * n_vars + gb)
    ka, kb = keys // n_vars, keys % n_vars
    kclass = var_type[ka] * n_types + var_type[kb]

    # rank of each block within its class (keys are sorted, so classes keep (a, b) order)
    order = np.argsort(kclass, kind="stable")
    cls_sorted = kclass[order]
    present, first = np.unique(cls_sorted, return_index=True)
    rank = np.empty(keys.size, np.int64)
    rank[order] = np.arange(keys.size) - np.repeat(first, np.diff(np.r_[first, keys.size]))
    class_index = {int(c): k for k, c in enumerate(present)}
    classes = tuple((int(c) // n_types, int(c) % n_types, int(n))
                    for c, n in zip(present, np.diff(np.r_[first, keys.size]), strict=True))
    sizes = [dims[a] * dims[b] * n for a, b, n in classes]
    class_start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

    # scalar entries of every block, in CSR order (row-major over (a, i, b, j))
    da, db = var_dim[ka], var_dim[kb]
    per = da * db
    blk = np.repeat(np.arange(keys.size), per)
    t = np.arange(blk.size) - np.repeat(np.cumsum(per) - per, per)
    i, j = t // db[blk], t % db[blk]
    rows = var_off[ka][blk] + i
    cols = var_off[kb][blk] + j
    csr_order = np.lexsort((cols, rows))
    rows, cols = rows[csr_order], cols[csr_order]
    cls = np.searchsorted(present, kclass)  # class id of each block
    flat = class_start[cls][blk] + rank[blk] * per[blk] + t
    perm = flat[csr_order]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=size))])
    diag_pos = np.nonzero(rows == cols)[0]
    assert diag_pos.size == size

    block_rows, block_cols = [], []
    for c in present:
        sel = order[cls_sorted == c]  # this class's blocks in rank order
        block_rows.append(np.asarray(ka[sel] - base[var_type[ka[sel]]], np.int32))
        block_cols.append(np.asarray(kb[sel] - base[var_type[kb[sel]]], np.int32))

    located = []
    for (ta, _, tb, _), (a, b) in zip(pairs, glob, strict=True):
        pos = np.searchsorted(keys, a * n_vars + b)
        located.append((class_index[ta * n_types + tb], rank[pos]))
    pattern = BlockPattern(
        dims=tuple(dims),
        classes=classes,
        size=size,
        nnz=int(rows.size),
        indices=np.asarray(cols, np.int32),
        indptr=np.asarray(indptr, np.int32),
        diag_pos=np.asarray(diag_pos, np.int32),
        perm=np.asarray(perm, np.int32),
        block_rows=tuple(block_rows),
        block_cols=tuple(block_cols),
    )
    return pattern, located


def scatter_blocks(
    blocks: list[Array], contributions: Sequence[tuple[int, Array, Array]],
    keep: Array | None = None,
) -> list[Array]:
    """Add ``values`` (m, da, db) at block indices ``idx`` (m,) of class ``c``; with
    ``keep`` (m,) only the rows where it is True (a chunk overlapping its predecessor)."""
    blocks = list(blocks)
    for c, idx, values in contributions:
        if keep is not None:
            idx = jnp.where(keep, idx, blocks[c].shape[0])  # out of range: dropped
        blocks[c] = blocks[c].at[idx].add(values.astype(blocks[c].dtype), mode="drop")
    return blocks
