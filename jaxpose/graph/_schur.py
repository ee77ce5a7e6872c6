"""Schur-complement elimination of one variable type (the points of bundle adjustment).

Order the tangent vector as (kept variables K, eliminated variables E). The damped normal
equations ``[[U, W], [Wᵀ, V]] [δK; δE] = [−gK; −gE]`` have a block-diagonal V (no factor
links two eliminated variables), so

    S δK = −gK + W V⁻¹ gE,   S = U − W V⁻¹ Wᵀ,       δE = V⁻¹ (−gE − Wᵀ δK).

W is kept as one block B = J_sᵀ J_e per (factor, kept slot) — an "entry" — with its kept
variable and its eliminated variable. S gets ``−Y_a B_bᵀ`` (Y = B V⁻¹) for every ordered
pair (a, b) of entries that share an eliminated variable; those pairs, their target blocks
in the reduced pattern and the reduced pattern itself are computed once on the host
(:func:`.analysis.build_schur`, stored as ``graph.structure.schur``); this module holds
only the jitted numerics.

Only the upper triangle of S is accumulated: U's upper blocks first, then the pairs
(sorted by target block, in chunks of ``analysis.CHUNK`` pairs under ``lax.scan``, so
memory stays bounded and the products stay in cache); the lower blocks are transposed
copies. On XLA:CPU
this makes one damped step about 1.5x cheaper than assembling the full H and factorising
it with CHOLMOD at 50 cameras × 10 000 points (see ``bench/ba.py``).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from .. import _small_linalg as small_linalg
from ._analysis import SchurStructure, split_tangent
from ._linear import solve_dense, solve_sparse_direct
from ._pattern import scatter_blocks

Array = jax.Array


PairBlock = Callable[[int, int, int], Array]
"""``block(k, s, t)``: factor group k's (m, d_s, d_t) blocks of H for its slots (s, t)
(blocks of fixed variables zero)."""


class SchurParts(NamedTuple):
    """The pieces of H that elimination reads (module docstring): ``u`` the kept–kept
    blocks as class arrays of the reduced pattern (upper classes filled, lower ones
    zero), ``v`` (n_e, d_e, d_e) the eliminated variables' diagonal blocks, ``w`` per
    kept type the entries B (n_k, d_k, d_e), sorted by kept variable. No damping."""

    u: list[Array]
    v: Array
    w: list[Array]


def schur_parts(graph: Any, block: PairBlock, dtype: Any) -> SchurParts:
    """:class:`SchurParts` of H = Σ of the per-factor ``block``s
    (:func:`~jaxpose.graph._problem.jtj_blocks` for the damped normal equations)."""
    return schur_parts_by_group(
        graph, dtype, lambda n, acc: add_group(graph, n, acc, partial(block, n)))


def schur_parts_by_group(graph: Any, dtype: Any, fill: Callable[[int, Any], Any],
                         zero: Array | None = None) -> SchurParts:
    """:class:`SchurParts` summed factor group by factor group: ``fill(n, (u, v, w))``
    returns the accumulators with group n's blocks added (:func:`add_group`); ``w`` holds
    the group's entries B, one zero (m, d_k, d_e) array per kept slot. A traced ``zero``
    is added to every accumulator (it keeps them from being program constants)."""
    st = graph.structure
    sc: SchurStructure = st.schur
    e, kept = sc.eliminated, sc.kept

    def traced(z: Array) -> Array:
        return z if zero is None else z + zero.astype(dtype)

    u = [traced(b) for b in sc.pattern.zeros(dtype)]
    v = traced(jnp.zeros((st.counts[e], st.dims[e], st.dims[e]), dtype))
    w_parts: list[list[Array]] = [[] for _ in kept]
    for n, f in enumerate(graph.factors):
        ws = sc.w_slots[n] if sc.e_slot[n] >= 0 else ()
        w = [traced(jnp.zeros((f.count, st.dims[kept[k]], st.dims[e]), dtype)) for _, k in ws]
        u, v, w = fill(n, (u, v, w))
        for wk, (_, k) in zip(w, ws, strict=True):
            w_parts[k].append(wk)
    return SchurParts(u, v, sort_entries(graph, w_parts, dtype))


def add_group(graph: Any, n: int, acc: Any, block: Callable[[int, int], Array],
              take: Callable[[Any], Any] | None = None, keep: Array | None = None,
              start: Array | None = None) -> Any:
    """``acc = (u, v, w)`` plus factor group n's blocks ``block(s, t)`` (m, d_s, d_t):
    kept–kept pairs into U, the eliminated diagonal into V, the entries B written into
    ``w``. For a chunk of the group: ``take`` selects its rows of a per-factor array,
    ``keep`` (m,) the rows to sum (see :func:`~jaxpose.graph._pattern.scatter_blocks`)
    and ``start`` its first factor (where its entries B go); by default the whole group."""
    sc: SchurStructure = graph.structure.schur
    take = (lambda a: a) if take is None else take
    u, v, w = acc
    u = scatter_blocks(u, [(c, take(idx), block(s, t))
                           for (s, t), c, idx in upper_pairs(graph, n)], keep)
    q = sc.e_slot[n]
    if q >= 0:
        v = scatter_blocks([v], [(0, take(graph.factors[n].indices[q]), block(q, q))], keep)[0]
        ws = sc.w_slots[n]
        w = [block(s, q).astype(wk.dtype) if start is None
             else jax.lax.dynamic_update_slice_in_dim(wk, block(s, q).astype(wk.dtype), start, 0)
             for wk, (s, _) in zip(w, ws, strict=True)]
    return u, v, w


def upper_pairs(graph: Any, n: int) -> list[tuple[tuple[int, int], int, Array]]:
    """``((s, t), class, (m,) block index)`` of factor group n's kept–kept slot pairs whose
    class lies in the upper triangle of the reduced pattern (the lower ones are mirrored)."""
    sc: SchurStructure = graph.structure.schur
    return [(pair, c, idx) for pair, c, idx in zip(sc.u_pairs[n], sc.u_class[n],
                                                    sc.u_index[n], strict=True)
            if sc.pattern.classes[c][0] <= sc.pattern.classes[c][1]]


def sort_entries(graph: Any, w_parts: list[list[Array]], dtype: Any) -> list[Array]:
    """Per kept type, the entries B of every factor group (``w_parts[k]``: (m, d_k, d_e)
    per group with an eliminated slot, in factor order) concatenated and sorted by kept
    variable."""
    st = graph.structure
    sc: SchurStructure = st.schur
    d_e = st.dims[sc.eliminated]
    return [jnp.concatenate(p)[o] if p else jnp.zeros((0, st.dims[t], d_e), dtype)
            for p, t, o in zip(w_parts, sc.kept, sc.w_order, strict=True)]


def schur_step(
    graph: Any,
    parts: SchurParts,
    g: Array,
    diag_add: Array,
    solve_reduced: Callable[[Array, Array, Array, Array], Array],
) -> Array:
    """Solve ``(H + diag(diag_add)) δ = −g`` by elimination, H given by its
    :class:`SchurParts` (:func:`schur_parts` of
    :func:`~jaxpose.graph._problem.jtj_blocks` for the damped normal equations; the exact
    Hessian's, assembled in chunks, in the implicit rule).

    ``diag_add`` (N,), in the graph's tangent layout, holds everything added to the
    diagonal of H (damping, and 1 for fixed variables, whose blocks are zero).
    ``solve_reduced(data, indices, indptr, b)`` solves the reduced CSR system.
    Returns δ (N,) in the graph's tangent layout."""
    st = graph.structure
    sc: SchurStructure = st.schur
    e, kept = sc.eliminated, sc.kept
    data, v_inv, w, y = reduced_system(graph, parts, diag_add)

    # reduced right-hand side and back-substitution
    g_blocks = split_tangent(st, g)
    g_e = g_blocks[e]
    rhs = [-g_blocks[t] for t in kept]
    for k in range(len(kept)):
        yg = jnp.einsum("nie,ne->ni", y[k], g_e[sc.w_point[k]])
        rhs[k] = rhs[k].at[sc.w_var[k]].add(yg)
    rhs_flat = jnp.concatenate([r.reshape(-1) for r in rhs])
    dk_flat = solve_reduced(data, sc.pattern.indices, sc.pattern.indptr, rhs_flat)
    dk, start = [], 0
    for t in kept:
        n = st.counts[t] * st.dims[t]
        dk.append(dk_flat[start : start + n].reshape(st.counts[t], st.dims[t]))
        start += n
    acc = -g_e
    for k in range(len(kept)):
        bt_dk = jnp.einsum("nie,ni->ne", w[k], dk[k][sc.w_var[k]])
        acc = acc.at[sc.w_point[k]].add(-bt_dk)
    de = jnp.einsum("nef,nf->ne", v_inv, acc)
    blocks = []
    for t in range(len(st.names)):
        blocks.append(de if t == e else dk[kept.index(t)])
    return jnp.concatenate([b.reshape(-1) for b in blocks])


def reduced_system(
    graph: Any, parts: SchurParts, diag_add: Array
) -> tuple[Array, Array, list[Array], list[Array]]:
    """The reduced matrix S = U − W V⁻¹ Wᵀ of ``H + diag(diag_add)`` (module docstring),
    H given by its :class:`SchurParts`.

    Returns (S as CSR values in ``graph.structure.schur.pattern``, V⁻¹ (n_e, d, d), the
    entries B per kept type, Y = B V⁻¹ per kept type)."""
    st = graph.structure
    sc: SchurStructure = st.schur
    e, kept = sc.eliminated, sc.kept
    d_e = st.dims[e]
    u, v, w = parts
    u = list(u)

    # damping (and the identity rows of fixed variables) on the diagonals of V and U
    add = split_tangent(st, diag_add)
    diag_idx = jnp.arange(d_e)
    v = v.at[:, diag_idx, diag_idx].add(add[e])
    v_inv = small_linalg.inv(v)

    # S = U − Σ_pairs Y_a B_bᵀ over the upper triangle, accumulated in chunks
    y = [jnp.einsum("nie,nef->nif", wk, v_inv[p]) for wk, p in zip(w, sc.w_point, strict=True)]
    s_blocks = u
    for (k1, k2, c), pa, pb, blk in zip(
        sc.pair_classes, sc.pair_a, sc.pair_b, sc.pair_block, strict=True
    ):
        def body(acc, chunk, k1=k1, k2=k2):
            ia, ib, ic = chunk
            prod = jnp.einsum("pie,pje->pij", y[k1][ia], w[k2][ib])
            return acc.at[ic].add(-prod, mode="drop", indices_are_sorted=True), None

        if pa.shape[0] == 1:  # one chunk: no loop
            s_blocks[c], _ = body(s_blocks[c], (pa[0], pb[0], blk[0]))
        else:
            s_blocks[c], _ = jax.lax.scan(body, s_blocks[c], (pa, pb, blk))
    for (c, m, same), mask, idx in zip(sc.mirror_classes, sc.mirror_mask, sc.mirror_index,
                                       strict=True):
        mirrored = s_blocks[m][idx].mT
        s_blocks[c] = (jnp.where(mask[:, None, None], mirrored, s_blocks[c]) if same
                       else mirrored)
    data = sc.pattern.csr(s_blocks)
    data = data.at[sc.pattern.diag_pos].add(
        jnp.concatenate([add[t].reshape(-1) for t in kept]))

    return data, v_inv, w, y


def reduced_solver(graph: Any, dense_max: int) -> Callable[[Array, Array, Array, Array], Array]:
    """The solver of the reduced system: CHOLMOD on CPU (single-threaded reference BLAS:
    the dense LAPACK Cholesky goes through a multi-threaded OpenBLAS whose spinning
    threads cost up to 100x on a loaded machine); dense Cholesky on accelerators when
    it has at most ``dense_max`` dimensions."""
    small = (graph.structure.schur.pattern.size <= dense_max
             and jax.default_backend() != "cpu")
    return solve_dense if small else solve_sparse_direct
