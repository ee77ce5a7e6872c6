"""Factor graphs: variables stacked per type, factors grouped per type, block-sparse algebra.

Layout of the tangent vector: variable types in sorted-name order; within a type,
variable ``i`` owns the contiguous slice ``offset + i·d : offset + (i+1)·d``.
The sparsity pattern of the Gauss–Newton matrix H = J̃ᵀJ̃ is computed once on the host
(numpy) when the graph is built; each iteration only fills in values, so jit compiles
one program whose size grows with the number of factor *types*, not factors.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..lie.base import LieGroup
from .factor import Factor

Array = jax.Array
Variables = dict[str, Any]  # name → LieGroup with batch (n,) or array (n, d)


def _tangent_dim(value: Any) -> int:
    return value.tangent_dim if isinstance(value, LieGroup) else int(value.shape[-1])


def _count(value: Any) -> int:
    return int(value.shape[0])


def _gather(value: Any, idx: Array) -> Any:
    if isinstance(value, LieGroup):
        return type(value)(value.data[idx])
    return value[idx]


def _retract(value: Any, delta: Array) -> Any:
    if isinstance(value, LieGroup):
        return value.retract(delta)
    return value + delta


class Structure(eqx.Module):
    """Static bookkeeping of a graph (index arrays are leaves; sizes are static)."""

    names: tuple[str, ...] = eqx.field(static=True)
    counts: tuple[int, ...] = eqx.field(static=True)
    dims: tuple[int, ...] = eqx.field(static=True)
    offsets: tuple[int, ...] = eqx.field(static=True)
    size: int = eqx.field(static=True)  # total tangent dimension N
    nnz: int = eqx.field(static=True)
    free: tuple[Array, ...]  # per type (n,) 1.0 for free, 0.0 for fixed variables
    csr_indices: Array  # (nnz,) column indices of H in CSR
    csr_indptr: Array  # (N + 1,)
    diag_pos: Array  # (N,) CSR positions of the diagonal
    block_pos: tuple[tuple[Array, ...], ...]  # per factor, per (s, t) slot pair: (m, ds, dt)
    contribution_order: Array  # permutation sorting all block entries by CSR position
    contribution_pos: Array  # their sorted CSR positions


class FactorGraph(eqx.Module):
    """A nonlinear least-squares problem over stacked variables.

    Args:
        factors: the factor groups (:class:`Factor`).
        variables: initial values, ``{name: group (n,) | array (n, d)}``.
        fixed: ``{name: indices}`` of variables held constant (gauge freedom).
    """

    factors: tuple[Factor, ...]
    variables: Variables
    structure: Structure

    def __init__(
        self,
        factors: Sequence[Factor],
        variables: Mapping[str, Any],
        fixed: Mapping[str, Any] | None = None,
    ):
        if not factors:
            raise ValueError("FactorGraph(factors): expected at least one Factor")
        variables = dict(variables)
        for name, value in variables.items():
            if isinstance(value, LieGroup):
                if len(value.shape) != 1:
                    raise ValueError(
                        f"FactorGraph(variables[{name!r}]): expected a batch of shape (n,), "
                        f"got {value.shape}"
                    )
            else:
                arr = jnp.asarray(value)
                if arr.ndim != 2:
                    raise ValueError(
                        f"FactorGraph(variables[{name!r}]): expected an array (n, d), got "
                        f"shape {arr.shape}"
                    )
                variables[name] = arr
        for k, f in enumerate(factors):
            if not isinstance(f, Factor):
                raise TypeError(
                    f"FactorGraph(factors[{k}]): expected Factor, got {type(f).__name__}"
                )
            for slot, idx in zip(f.slots, f.indices, strict=True):
                if slot not in variables:
                    raise KeyError(
                        f"FactorGraph: factor {f.name!r} uses variable type {slot!r}, "
                        f"not among {sorted(variables)}"
                    )
                n = _count(variables[slot])
                idx_np = np.asarray(idx)
                if idx_np.size and (idx_np.min() < 0 or idx_np.max() >= n):
                    raise IndexError(
                        f"FactorGraph: factor {f.name!r} references {slot!r} index "
                        f"{int(idx_np.max() if idx_np.max() >= n else idx_np.min())}, but only "
                        f"{n} variables of that type exist"
                    )
        self.factors = tuple(factors)
        self.variables = variables
        self.structure = _build_structure(self.factors, variables, dict(fixed or {}))

    @property
    def size(self) -> int:
        """Total tangent dimension."""
        return self.structure.size


def _build_structure(
    factors: tuple[Factor, ...], variables: Variables, fixed: dict[str, Any]
) -> Structure:
    names = tuple(sorted(variables))
    counts = tuple(_count(variables[n]) for n in names)
    dims = tuple(_tangent_dim(variables[n]) for n in names)
    offsets = tuple(int(x) for x in np.concatenate([[0], np.cumsum(np.multiply(counts, dims))]))
    size = offsets[-1]
    type_of = {n: k for k, n in enumerate(names)}
    free = []
    for n, c in zip(names, counts, strict=True):
        mask = np.ones(c)
        if n in fixed:
            idx = np.asarray(fixed[n], dtype=np.int64).reshape(-1)
            if idx.size and (idx.min() < 0 or idx.max() >= c):
                raise IndexError(f"FactorGraph(fixed[{n!r}]): index out of range for {c} variables")
            mask[idx] = 0.0
        free.append(jnp.asarray(mask))
    for n in fixed:
        if n not in type_of:
            raise KeyError(f"FactorGraph(fixed): unknown variable type {n!r}")

    # Dof indices of every (factor, slot, row-entry) → (m, d) global rows.
    def dofs(slot: str, idx: np.ndarray) -> np.ndarray:
        k = type_of[slot]
        return offsets[k] + idx[:, None] * dims[k] + np.arange(dims[k])[None, :]

    rows_all, cols_all, entry_blocks = [], [], []
    for f in factors:
        d_slots = [dofs(s, np.asarray(i)) for s, i in zip(f.slots, f.indices, strict=True)]
        pairs = []
        for a in d_slots:
            for b in d_slots:
                r = np.broadcast_to(a[:, :, None], (a.shape[0], a.shape[1], b.shape[1]))
                c = np.broadcast_to(b[:, None, :], r.shape)
                rows_all.append(r.reshape(-1))
                cols_all.append(c.reshape(-1))
                pairs.append((r, c))
        entry_blocks.append(pairs)
    diag = np.arange(size)
    rows = np.concatenate([*rows_all, diag])
    cols = np.concatenate([*cols_all, diag])
    keys = np.unique(rows.astype(np.int64) * size + cols)
    csr_rows, csr_cols = keys // size, keys % size
    indptr = np.zeros(size + 1, dtype=np.int64)
    np.add.at(indptr, csr_rows + 1, 1)
    indptr = np.cumsum(indptr)

    def position(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        return np.searchsorted(keys, r.astype(np.int64) * size + c)

    pos_np = [[position(r, c) for r, c in pairs] for pairs in entry_blocks]
    block_pos = tuple(tuple(jnp.asarray(p, jnp.int32) for p in pairs) for pairs in pos_np)
    flat_pos = np.concatenate([p.reshape(-1) for pairs in pos_np for p in pairs])
    order = np.argsort(flat_pos, kind="stable")
    return Structure(
        names=names,
        counts=counts,
        dims=dims,
        offsets=offsets,
        size=size,
        nnz=int(keys.size),
        free=tuple(free),
        csr_indices=jnp.asarray(csr_cols, jnp.int32),
        csr_indptr=jnp.asarray(indptr, jnp.int32),
        diag_pos=jnp.asarray(position(diag, diag), jnp.int32),
        block_pos=block_pos,
        contribution_order=jnp.asarray(order, jnp.int32),
        contribution_pos=jnp.asarray(flat_pos[order], jnp.int32),
    )


# ----------------------------------------------------------------------------------
# Evaluation
# ----------------------------------------------------------------------------------
class Linearization(eqx.Module):
    """Whitened residuals and Jacobian blocks of every factor group at one point."""

    residuals: tuple[Array, ...]  # per factor group: (m, r) whitened (and robustified)
    jacobians: tuple[tuple[Array, ...], ...]  # per group, per slot: (m, r, d_slot)
    cost: Array  # scalar 0.5·Σ ρ(|r̃|²)


def _robust(kernel: Any, r: Array) -> tuple[Array, Array]:
    """(ρ(s), sqrt(ρ'(s))) for s = |r|² per row; identity when kernel is None."""
    s = jnp.sum(r * r, -1)
    if kernel is None:
        return s, jnp.ones_like(s)
    rho, drho = jax.vmap(jax.value_and_grad(kernel))(s)
    return rho, jnp.sqrt(jnp.maximum(drho, 0.0))


def factor_residuals(factor: Factor, variables: Variables) -> Array:
    """Whitened residuals (m, r) of one factor group (no kernel)."""
    vals = [_gather(variables[s], i) for s, i in zip(factor.slots, factor.indices, strict=True)]
    r = jax.vmap(lambda *a: factor.residual(*a[:-1], a[-1]))(*vals, factor.data)
    if factor.sqrt_info is not None:
        r = jnp.einsum("mij,mj->mi", factor.sqrt_info.astype(r.dtype), r)
    return r


def cost(graph: FactorGraph, variables: Variables) -> Array:
    """0.5 · Σ ρ(rᵀΩr) over all factors."""
    total = 0.0
    for f in graph.factors:
        rho, _ = _robust(f.kernel, factor_residuals(f, variables))
        total = total + 0.5 * jnp.sum(rho)
    return jnp.asarray(total)


def linearize(graph: FactorGraph, variables: Variables) -> Linearization:
    """Residuals and tangent-space Jacobian blocks (fixed variables get zero blocks).

    Robust kernels use the square-root IRLS weighting (FastTriggs): residual and
    Jacobian rows are scaled by sqrt(ρ'(s))."""
    st = graph.structure
    type_of = {n: k for k, n in enumerate(st.names)}
    residuals, jacobians, total = [], [], 0.0
    for f in graph.factors:
        vals = [_gather(variables[s], i) for s, i in zip(f.slots, f.indices, strict=True)]

        def one(*args: Any, f: Factor = f) -> tuple[Array, tuple[Array, ...]]:
            point, data = args[:-1], args[-1]
            if f.jacobian is not None:
                r, *jac = f.jacobian(*point, data)
                return r, tuple(jac)
            zeros = tuple(jnp.zeros((_tangent_dim_single(p),), _dtype(p)) for p in point)

            def res(deltas: tuple[Array, ...]) -> tuple[Array, Array]:
                moved = [_retract(p, d) for p, d in zip(point, deltas, strict=True)]
                r = f.residual(*moved, data)
                return r, r

            jac, r = jax.jacfwd(res, has_aux=True)(zeros)
            return r, jac

        r, jac = jax.vmap(one)(*vals, f.data)
        if f.sqrt_info is not None:
            s = f.sqrt_info.astype(r.dtype)
            r = jnp.einsum("mij,mj->mi", s, r)
            jac = tuple(jnp.einsum("mij,mjk->mik", s, j) for j in jac)
        rho, w = _robust(f.kernel, r)
        if f.kernel is not None:
            r = r * w[:, None]
            jac = tuple(j * w[:, None, None] for j in jac)
        jac = tuple(
            j * st.free[type_of[slot]][idx][:, None, None].astype(j.dtype)
            for j, slot, idx in zip(jac, f.slots, f.indices, strict=True)
        )
        residuals.append(r)
        jacobians.append(jac)
        total = total + 0.5 * jnp.sum(rho)
    return Linearization(tuple(residuals), tuple(jacobians), jnp.asarray(total))


def _tangent_dim_single(p: Any) -> int:
    return p.tangent_dim if isinstance(p, LieGroup) else int(p.shape[-1])


def _dtype(p: Any) -> Any:
    return p.dtype


def split(graph: FactorGraph, flat: Array) -> tuple[Array, ...]:
    """Flat tangent (N,) → per-type blocks (n, d)."""
    st = graph.structure
    return tuple(
        flat[st.offsets[k] : st.offsets[k + 1]].reshape(st.counts[k], st.dims[k])
        for k in range(len(st.names))
    )


def join(blocks: Sequence[Array]) -> Array:
    """Per-type blocks (n, d) → flat tangent (N,)."""
    return jnp.concatenate([b.reshape(-1) for b in blocks])


def gradient(graph: FactorGraph, lin: Linearization) -> Array:
    """g = J̃ᵀ r̃ (N,)."""
    st = graph.structure
    type_of = {n: k for k, n in enumerate(st.names)}
    dtype = lin.cost.dtype
    out = [jnp.zeros((c, d), dtype) for c, d in zip(st.counts, st.dims, strict=True)]
    for f, r, jac in zip(graph.factors, lin.residuals, lin.jacobians, strict=True):
        for slot, idx, j in zip(f.slots, f.indices, jac, strict=True):
            k = type_of[slot]
            out[k] = out[k].at[idx].add(jnp.einsum("mri,mr->mi", j, r))
    return join(out)


def block_diagonal(graph: FactorGraph, lin: Linearization) -> tuple[Array, ...]:
    """Diagonal blocks of H per type: (n, d, d)."""
    st = graph.structure
    type_of = {n: k for k, n in enumerate(st.names)}
    dtype = lin.cost.dtype
    out = [jnp.zeros((c, d, d), dtype) for c, d in zip(st.counts, st.dims, strict=True)]
    for f, jac in zip(graph.factors, lin.jacobians, strict=True):
        for slot, idx, j in zip(f.slots, f.indices, jac, strict=True):
            k = type_of[slot]
            out[k] = out[k].at[idx].add(jnp.einsum("mri,mrj->mij", j, j))
    return tuple(out)


def hessian_vector(graph: FactorGraph, lin: Linearization, v: Array) -> Array:
    """H v = J̃ᵀ(J̃ v) without forming H (N,)."""
    st = graph.structure
    type_of = {n: k for k, n in enumerate(st.names)}
    vb = split(graph, v)
    out = [jnp.zeros_like(b) for b in vb]
    for f, jac in zip(graph.factors, lin.jacobians, strict=True):
        u = 0.0
        for slot, idx, j in zip(f.slots, f.indices, jac, strict=True):
            u = u + jnp.einsum("mri,mi->mr", j, vb[type_of[slot]][idx])
        for slot, idx, j in zip(f.slots, f.indices, jac, strict=True):
            k = type_of[slot]
            out[k] = out[k].at[idx].add(jnp.einsum("mri,mr->mi", j, u))
    return join(out)


def csr_values(graph: FactorGraph, lin: Linearization) -> Array:
    """Values of H in the precomputed CSR pattern (nnz,).

    All block products are concatenated and summed into their CSR positions with one
    sorted ``segment_sum`` (the permutation is precomputed with the pattern)."""
    st = graph.structure
    parts = [
        jnp.einsum("mri,mrj->mij", a, b).reshape(-1)
        for jac in lin.jacobians
        for a in jac
        for b in jac
    ]
    contributions = jnp.concatenate(parts)[st.contribution_order]
    return jax.ops.segment_sum(
        contributions, st.contribution_pos, num_segments=st.nnz, indices_are_sorted=True
    )


def retract_all(graph: FactorGraph, variables: Variables, step: Array) -> Variables:
    """Apply a flat tangent step to every variable type (fixed ones have zero steps)."""
    blocks = split(graph, step)
    return {
        name: _retract(
            variables[name], blocks[k] * graph.structure.free[k][:, None].astype(blocks[k].dtype)
        )
        for k, name in enumerate(graph.structure.names)
    }
