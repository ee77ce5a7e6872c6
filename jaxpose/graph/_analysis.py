"""Analysis phase of a factor graph: the host-side (numpy) structure built once.

Everything here depends only on the graph's shape — variable types, counts, tangent
dimensions, factor slots and indices — never on values: the tangent layout (types in
sorted-name order; variable ``i`` of a type owns ``offset + i·d : offset + (i+1)·d``),
the free/fixed masks, the block-sparsity pattern of H = J̃ᵀJ̃ with the CSR assembly plan
(:mod:`.pattern`), and, when a variable type is eliminated, the Schur-complement
bookkeeping (:class:`SchurStructure`). :mod:`.problem` (evaluation) and :mod:`.schur`
(elimination) both build on this module; it imports neither.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..lie._base import LieGroup
from ._pattern import BlockPattern, build_pattern

Array = jax.Array
Variables = dict[str, Any]  # name → LieGroup with batch (n,) or array (n, d)
CHUNK = 4096  # Schur entry pairs per accumulation step (products stay in cache)


def tangent_dim(value: Any) -> int:
    """Tangent dimension d of a variable: a group (batch) or an array (..., d)."""
    return value.tangent_dim if isinstance(value, LieGroup) else int(value.shape[-1])


def count(value: Any) -> int:
    """Number n of stacked variables in a group batch (n,) or an array (n, d)."""
    return int(value.shape[0])


class Structure(eqx.Module):
    """Static bookkeeping of a graph (index arrays are leaves; sizes are static)."""

    names: tuple[str, ...] = eqx.field(static=True)
    counts: tuple[int, ...] = eqx.field(static=True)
    dims: tuple[int, ...] = eqx.field(static=True)
    offsets: tuple[int, ...] = eqx.field(static=True)
    size: int = eqx.field(static=True)  # total tangent dimension N
    free: tuple[Array, ...]  # per type (n,) 1.0 for free, 0.0 for fixed variables
    fixed_counts: tuple[int, ...] = eqx.field(static=True)  # per type: how many are fixed
    pattern: BlockPattern  # block-sparse pattern of H = J̃ᵀJ̃
    # per factor group, per ordered slot pair (s, t) (row-major): class id and (m,) blocks
    block_class: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    block_index: tuple[tuple[Array, ...], ...]
    schur: SchurStructure | None = None  # when the graph eliminates a variable type
    # per factor group, per slot: index_checksum of the indices the structure was built from
    index_sums: tuple[tuple[int, ...], ...] = eqx.field(static=True, default=())

    @property
    def nnz(self) -> int:
        return self.pattern.nnz

    @property
    def csr_indices(self) -> Array:
        return self.pattern.indices

    @property
    def csr_indptr(self) -> Array:
        return self.pattern.indptr

    @property
    def diag_pos(self) -> Array:
        return self.pattern.diag_pos


def slot_pairs(n_slots: int) -> list[tuple[int, int]]:
    """Ordered slot pairs (s, t) in the order of ``Structure.block_class``."""
    return [(s, t) for s in range(n_slots) for t in range(n_slots)]


def fixed_indices(value: Any, what: str) -> np.ndarray:
    """Indices of fixed variables as int64 (flattened), ``what`` naming the argument in
    errors: integers only (a boolean mask or floats would be cast to indices silently),
    concrete."""
    if isinstance(value, jax.core.Tracer):
        raise TypeError(f"{what}: indices must be concrete (numpy or Python ints), not "
                        f"traced: a graph's structure is static")
    idx = np.asarray(value)
    if idx.size and not np.issubdtype(idx.dtype, np.integer):
        hint = " (a boolean mask: pass np.flatnonzero(mask))" if idx.dtype == bool else ""
        raise ValueError(f"{what}: expected integer indices, got dtype {idx.dtype}{hint}")
    return idx.astype(np.int64).reshape(-1)


def build_structure(
    factors: Sequence[Any], variables: Variables, fixed: Mapping[str, Any],
    eliminate: str | None = None,
) -> Structure:
    """Host (numpy) analysis of a graph: variable layout, free masks, the block pattern
    of H and, with ``eliminate``, the Schur bookkeeping (:func:`build_schur`)."""
    names = tuple(sorted(variables))
    counts = tuple(count(variables[n]) for n in names)
    dims = tuple(tangent_dim(variables[n]) for n in names)
    offsets = tuple(int(x) for x in np.concatenate([[0], np.cumsum(np.multiply(counts, dims))]))
    type_of = {n: k for k, n in enumerate(names)}
    for n in fixed:
        if n not in type_of:
            raise KeyError(f"FactorGraph(fixed): unknown variable type {n!r}")
    free = []
    for n, c in zip(names, counts, strict=True):
        mask = np.ones(c)
        if n in fixed:
            idx = fixed_indices(fixed[n], f"FactorGraph(fixed[{n!r}])")
            if idx.size and (idx.min() < 0 or idx.max() >= c):
                raise IndexError(f"FactorGraph(fixed[{n!r}]): index out of range for {c} variables")
            mask[idx] = 0.0
        free.append(np.asarray(mask))

    pairs = []
    for f in factors:
        for s, t in slot_pairs(len(f.slots)):
            pairs.append((type_of[f.slots[s]], np.asarray(f.indices[s]),
                          type_of[f.slots[t]], np.asarray(f.indices[t])))
    pattern, located = build_pattern(counts, dims, pairs)
    block_class, block_index, k = [], [], 0
    for f in factors:
        n_pairs = len(slot_pairs(len(f.slots)))
        block_class.append(tuple(c for c, _ in located[k : k + n_pairs]))
        block_index.append(tuple(np.asarray(i, np.int32) for _, i in located[k : k + n_pairs]))
        k += n_pairs
    schur = None
    if eliminate is not None:
        if eliminate not in type_of:
            raise KeyError(
                f"FactorGraph(eliminate={eliminate!r}): not a variable type; expected one of "
                f"{list(names)}"
            )
        schur = build_schur(factors, names, counts, dims, eliminate)
    return Structure(
        names=names,
        counts=counts,
        dims=dims,
        offsets=offsets,
        size=offsets[-1],
        free=tuple(free),
        fixed_counts=tuple(int(np.sum(m == 0.0)) for m in free),
        pattern=pattern,
        block_class=tuple(block_class),
        block_index=tuple(block_index),
        schur=schur,
        index_sums=tuple(tuple(int(index_checksum(i)) for i in f.indices) for f in factors),
    )


def index_checksum(idx: Any, xp: Any = np) -> Any:
    """A position-weighted uint32 checksum of an index array (wrapping arithmetic, equal
    in NumPy (``xp=np``) and JAX (``xp=jnp``)): whether a factor's indices are still
    those its graph's structure was built from."""
    i = xp.ravel(xp.asarray(idx)).astype(xp.uint32)
    w = (xp.arange(i.shape[0], dtype=xp.uint32) * xp.asarray(2654435761, xp.uint32)
         + xp.asarray(2246822519, xp.uint32))
    return xp.sum((i + xp.asarray(1, xp.uint32)) * w, dtype=xp.uint32)


class SchurStructure(eqx.Module):
    """Host-computed bookkeeping of the elimination (see the module docstring).

    Type numbers ``k`` below index ``kept`` (the kept variable types, sorted by name)."""

    eliminated: int = eqx.field(static=True)  # index of the eliminated type in the names
    kept: tuple[int, ...] = eqx.field(static=True)  # indices of the kept types
    pattern: BlockPattern  # the reduced system S over the kept types
    e_slot: tuple[int, ...] = eqx.field(static=True)  # per factor: slot of type E or -1
    # per factor, per ordered pair of kept slots (s, t): reduced class and (m,) blocks
    u_pairs: tuple[tuple[tuple[int, int], ...], ...] = eqx.field(static=True)
    u_class: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    u_index: tuple[tuple[Array, ...], ...]
    # per factor, per kept slot s (factors with an E slot): (s, kept type k); the entries
    # of W_k are these (factor, slot) blocks concatenated in factor order, then sorted by
    # kept variable (``w_order``)
    w_slots: tuple[tuple[tuple[int, int], ...], ...] = eqx.field(static=True)
    w_counts: tuple[int, ...] = eqx.field(static=True)  # entries per kept type
    w_order: tuple[Array, ...]  # per kept type: factor-order entry of each sorted entry
    w_point: tuple[Array, ...]  # per kept type: (n_k,) eliminated variable of each entry
    w_var: tuple[Array, ...]  # per kept type: (n_k,) kept variable of each entry
    # upper pair classes (k1 <= k2): (k1, k2, reduced class); index arrays (chunks, size)
    # of the entries a, b and the target block (padding: block index n_blocks, dropped)
    pair_classes: tuple[tuple[int, int, int], ...] = eqx.field(static=True)
    pair_a: tuple[Array, ...]
    pair_b: tuple[Array, ...]
    pair_block: tuple[Array, ...]
    # lower classes: (class, mirror class, same type); lower-block mask (n,) (used when the
    # class is its own mirror) and the mirror block of every block (n,)
    mirror_classes: tuple[tuple[int, int, bool], ...] = eqx.field(static=True)
    mirror_mask: tuple[Array, ...]
    mirror_index: tuple[Array, ...]


def build_schur(
    factors: Sequence[Any],
    names: tuple[str, ...],
    counts: tuple[int, ...],
    dims: tuple[int, ...],
    eliminate: str,
) -> SchurStructure:
    """Bookkeeping for eliminating the variable type ``eliminate`` (host, numpy)."""
    e = names.index(eliminate)
    kept = tuple(k for k in range(len(names)) if k != e)
    if not kept:
        raise ValueError(f"FactorGraph(eliminate={eliminate!r}): no other variable type to keep")
    kpos = {t: k for k, t in enumerate(kept)}
    e_slot, u_pairs, u_list, w_slots = [], [], [], []
    w_point: list[list[np.ndarray]] = [[] for _ in kept]
    w_var: list[list[np.ndarray]] = [[] for _ in kept]
    w_counts = [0] * len(kept)
    for f in factors:
        slots_e = [s for s, n in enumerate(f.slots) if n == eliminate]
        if len(slots_e) > 1:
            raise ValueError(
                f"FactorGraph(eliminate={eliminate!r}): factor {f.name!r} links two "
                f"{eliminate!r} variables, so their block of H is not block-diagonal"
            )
        q = slots_e[0] if slots_e else -1
        e_slot.append(q)
        ks = [s for s in range(len(f.slots)) if s != q]
        pairs = tuple((s, t) for s in ks for t in ks)
        u_pairs.append(pairs)
        for s, t in pairs:
            u_list.append((kpos[names.index(f.slots[s])], np.asarray(f.indices[s]),
                           kpos[names.index(f.slots[t])], np.asarray(f.indices[t])))
        ws = []
        if q >= 0:
            for s in ks:
                k = kpos[names.index(f.slots[s])]
                ws.append((s, k))
                w_counts[k] += f.count
                w_point[k].append(np.asarray(f.indices[q], np.int64))
                w_var[k].append(np.asarray(f.indices[s], np.int64))
        w_slots.append(tuple(ws))
    cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0, np.int64)
    # entries of each kept type sorted by their kept variable: the pairs of one target
    # block then read two compact regions (cache locality of the pair gathers)
    w_order = [np.argsort(cat(x), kind="stable") for x in w_var]
    wp = [cat(x)[o] for x, o in zip(w_point, w_order, strict=True)]
    wv = [cat(x)[o] for x, o in zip(w_var, w_order, strict=True)]

    # all ordered pairs of entries sharing an eliminated variable
    g_type = np.concatenate([np.full(n, k) for k, n in enumerate(w_counts)]).astype(np.int64)
    g_local = np.concatenate([np.arange(n) for n in w_counts]).astype(np.int64)
    g_point, g_var = cat(wp), cat(wv)
    order = np.argsort(g_point, kind="stable")
    pts = g_point[order]
    start = np.searchsorted(pts, pts, "left")
    cnt = np.searchsorted(pts, pts, "right") - start
    rep = np.repeat(np.arange(order.size), cnt)
    partner = start[rep] + np.arange(rep.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    a, b = order[rep], order[partner]
    pair_groups = []
    for k1 in range(len(kept)):
        for k2 in range(len(kept)):
            sel = (g_type[a] == k1) & (g_type[b] == k2)
            if sel.any():
                pair_groups.append((k1, k2, g_local[a[sel]], g_local[b[sel]],
                                    g_var[a[sel]], g_var[b[sel]]))
    kc = [counts[t] for t in kept]
    kd = [dims[t] for t in kept]
    pattern, located = build_pattern(
        kc, kd, u_list + [(k1, va, k2, vb) for k1, k2, _, _, va, vb in pair_groups]
    )
    u_class, u_index, i = [], [], 0
    for pairs in u_pairs:
        u_class.append(tuple(c for c, _ in located[i : i + len(pairs)]))
        u_index.append(tuple(np.asarray(x, np.int32) for _, x in located[i : i + len(pairs)]))
        i += len(pairs)
    pair_classes, pa, pb, pblk = [], [], [], []
    for (k1, k2, la, lb, va, vb), (c, blk) in zip(pair_groups, located[i:], strict=True):
        if k1 > k2:
            continue
        keep = np.flatnonzero(va <= vb if k1 == k2 else np.ones(va.size, bool))
        keep = keep[np.argsort(blk[keep], kind="stable")]
        n_blocks = pattern.classes[c][2]
        pair_classes.append((k1, k2, c))
        pa.append(_chunked(la[keep], 0))
        pb.append(_chunked(lb[keep], 0))
        pblk.append(_chunked(blk[keep], n_blocks))
    mirror_classes, mirror_mask, mirror_index = [], [], []
    for c, (ka, kb, _) in enumerate(pattern.classes):
        if ka < kb:
            continue
        m = pattern.class_id(kb, ka)
        rows, cols = _block_coords(pattern, c)
        mrows, mcols = _block_coords(pattern, m)
        key = mrows * (kc[kb] + kc[ka]) + mcols
        order = np.argsort(key)
        idx = order[np.searchsorted(key[order], cols * (kc[kb] + kc[ka]) + rows)]
        mirror_classes.append((c, m, ka == kb))
        mirror_mask.append(np.asarray(rows > cols))
        mirror_index.append(np.asarray(idx, np.int32))
    return SchurStructure(
        eliminated=e,
        kept=kept,
        pattern=pattern,
        e_slot=tuple(e_slot),
        u_pairs=tuple(u_pairs),
        u_class=tuple(u_class),
        u_index=tuple(u_index),
        w_slots=tuple(w_slots),
        w_counts=tuple(w_counts),
        w_order=tuple(np.asarray(o, np.int32) for o in w_order),
        w_point=tuple(np.asarray(x, np.int32) for x in wp),
        w_var=tuple(np.asarray(x, np.int32) for x in wv),
        pair_classes=tuple(pair_classes),
        pair_a=tuple(pa),
        pair_b=tuple(pb),
        pair_block=tuple(pblk),
        mirror_classes=tuple(mirror_classes),
        mirror_mask=tuple(mirror_mask),
        mirror_index=tuple(mirror_index),
    )


def _chunked(x: np.ndarray, fill: int) -> Array:
    """(chunks, size) int32 padded with ``fill``; size = CHUNK, or the next power of two
    of x.size when that is smaller (small problems do not pay for a whole chunk)."""
    size = min(CHUNK, 1 << max(int(x.size) - 1, 0).bit_length())
    pad = (-x.size) % size
    return np.asarray(np.pad(x, (0, pad), constant_values=fill).reshape(-1, size), np.int32)


def _block_coords(pattern: BlockPattern, c: int) -> tuple[np.ndarray, np.ndarray]:
    """(row variable, column variable) of every block of class c (within their types)."""
    return np.asarray(pattern.block_rows[c]), np.asarray(pattern.block_cols[c])


def split_tangent(st: Structure, flat: Array) -> tuple[Array, ...]:
    """Flat tangent (N,) → per-type blocks (n, d) in the layout of ``st``."""
    return tuple(
        flat[st.offsets[k] : st.offsets[k + 1]].reshape(st.counts[k], st.dims[k])
        for k in range(len(st.names))
    )


def join(blocks: Sequence[Array]) -> Array:
    """Per-type blocks (n, d) → flat tangent (N,)."""
    return jnp.concatenate([b.reshape(-1) for b in blocks])
