"""Factor graphs: variables stacked per type, factors grouped per type, block-sparse algebra.

Layout of the tangent vector: variable types in sorted-name order; within a type,
variable ``i`` owns the contiguous slice ``offset + i·d : offset + (i+1)·d``.
The block-sparsity pattern of the Gauss–Newton matrix H = J̃ᵀJ̃ (:mod:`.pattern`) is
computed once on the host (numpy) when the graph is built (:mod:`.analysis`); each
iteration only fills in
values, so jit compiles one program whose size grows with the number of factor *types*,
not factors.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._dtypes import inexact
from ..lie import manifold
from ..lie._base import LieGroup, small_matmul, small_matvec
from ..lie.series import computed_once
from ._analysis import (
    Structure,
    Variables,
    build_structure,
    count,
    index_checksum,
    join,
    slot_pairs,
    split_tangent,
    tangent_dim,
)
from ._factor import Factor
from ._pattern import scatter_blocks

Array = jax.Array


def _gather(value: Any, idx: Array) -> Any:
    if isinstance(value, LieGroup):
        return type(value)(value.data[idx])
    return value[idx]


def _retract(value: Any, delta: Array, method: str = "retract") -> Any:
    """``value ⊕ delta`` by :mod:`jaxpose.lie.manifold`'s ``method``: ``retract``, or
    ``retract_linear`` / ``retract_quadratic`` inside first / second derivatives at δ = 0."""
    return getattr(manifold, method)(value, delta)


class FactorGraph(eqx.Module):
    """A nonlinear least-squares problem over stacked variables.

    Args:
        factors: the factor groups (:class:`Factor`).
        variables: initial values, ``{name: group (n,) | array (n, d)}``.
        fixed: ``{name: indices}`` of variables held constant (gauge freedom).
        eliminate: optional variable type (e.g. the points of bundle adjustment) to
            eliminate with the Schur complement (``solve(linear_solver="schur")``); no
            factor may link two variables of this type.
    """

    factors: tuple[Factor, ...]
    variables: Variables
    structure: Structure

    def __init__(
        self,
        factors: Sequence[Factor],
        variables: Mapping[str, Any],
        fixed: Mapping[str, Any] | None = None,
        eliminate: str | None = None,
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
                arr = inexact(jnp.asarray(value))  # integer starts, as least_squares
                if arr.ndim != 2:
                    raise ValueError(
                        f"FactorGraph(variables[{name!r}]): expected an array (n, d), got "
                        f"shape {arr.shape}"
                    )
                variables[name] = arr
            if count(variables[name]) == 0:
                raise ValueError(f"FactorGraph(variables[{name!r}]): expected at least one "
                                 "variable, got an empty batch (leave the type out)")
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
                n = count(variables[slot])
                idx_np = np.asarray(idx)
                if idx_np.size and (idx_np.min() < 0 or idx_np.max() >= n):
                    raise IndexError(
                        f"FactorGraph: factor {f.name!r} references {slot!r} index "
                        f"{int(idx_np.max() if idx_np.max() >= n else idx_np.min())}, but only "
                        f"{n} variables of that type exist"
                    )
            _check_information(f, variables)
        self.factors = tuple(factors)
        self.variables = variables
        self.structure = build_structure(self.factors, variables, dict(fixed or {}), eliminate)

    @property
    def size(self) -> int:
        """Total tangent dimension."""
        return self.structure.size


# ----------------------------------------------------------------------------------
# Evaluation
# ----------------------------------------------------------------------------------
def _check_information(f: Factor, variables: Variables) -> None:
    """Raise unless ``f``'s information matrices are r × r, r its residual's dimension
    (the whitening product would otherwise use only the first k components)."""
    if f.sqrt_info is None:
        return
    dim, k = residual_dim(f, variables), f.sqrt_info.shape[-1]
    if dim is not None and dim != k:
        raise ValueError(
            f"FactorGraph: factor {f.name!r} has {dim}-dimensional residuals but {k} × {k} "
            f"information matrices; Factor(information) must be ({f.count}, {dim}, {dim}) or "
            f"({dim}, {dim})")


_RESIDUAL_DIMS: dict[Any, int | None] = {}


def residual_dim(f: Factor, variables: Variables) -> int | None:
    """Dimension of one residual of ``f`` (None unless it is 1-D), from its shapes alone
    (``jax.eval_shape`` of one factor), remembered per residual function and argument
    types and shapes (tracing it costs tens of milliseconds)."""
    args = [variables[s] for s in f.slots] + [f.data]
    one = [jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype), x) for x in args]
    try:
        key = (f.residual, tuple(jax.tree.structure(x) for x in one),
               tuple(jax.tree.leaves(one)))
        hash(key)
    except TypeError:  # an unhashable residual function: not remembered
        key = None
    if key is None or key not in _RESIDUAL_DIMS:
        res = jax.eval_shape(lambda *a: f.residual(*a[:-1], a[-1]), *one)
        dim = res.shape[0] if res.ndim == 1 else None
        if key is None:
            return dim
        if len(_RESIDUAL_DIMS) >= 256:  # residuals defined anew in a loop: stay small
            _RESIDUAL_DIMS.clear()
        _RESIDUAL_DIMS[key] = dim
    return _RESIDUAL_DIMS[key]


def check_variables(graph: FactorGraph, variables: Any, caller: str) -> None:
    """Raise unless ``variables`` holds the graph's variable types, each of the same kind
    (group class or plain array) and shape as ``graph.variables``: the factors' index
    gathers would clamp a shorter batch silently. Shapes are static: works under jit. The
    graph's own variables and information are checked against its structure too."""
    _check_built_shapes(graph, caller)
    if not isinstance(variables, Mapping) or set(variables) != set(graph.variables):
        got = sorted(variables) if isinstance(variables, Mapping) else type(variables).__name__
        raise ValueError(f"{caller}: expected a mapping with the graph's variable types "
                         f"{sorted(graph.variables)}, got {got}")
    for name, ref in graph.variables.items():
        value = variables[name]
        if _kind(value) != _kind(ref):
            raise ValueError(f"{caller}: variables[{name!r}]: expected {_kind(ref)} like "
                             f"graph.variables, got {_kind(value)}")


def check_structure(graph: FactorGraph, caller: str) -> FactorGraph:
    """``graph``, raising unless its variables and factors still match the structure built
    from them when it was made: ``eqx.tree_at`` (or a pytree transformation) can replace
    a factor's indices or information, or the variables, without rebuilding it, and H
    would then be assembled in the old pattern — a wrong solution and wrong marginals
    under a converged status. The indices are compared by checksum, now where they are
    known and at run time (``eqx.error_if``) where they are traced; the variables' counts
    and dimensions and the information sizes by :func:`check_variables`, which every
    caller runs next."""
    traced = []
    for k, (f, sums) in enumerate(zip(graph.factors, graph.structure.index_sums, strict=True)):
        for idx, want in zip(f.indices, sums, strict=True):
            if isinstance(idx, jax.core.Tracer):
                traced.append(index_checksum(idx, jnp) != np.uint32(want))
            elif int(index_checksum(np.asarray(idx))) != want:
                raise ValueError(_stale_indices(caller, k))
    if traced:
        graph = eqx.error_if(graph, jnp.any(jnp.stack(traced)), _stale_indices(caller, None))
    return graph


def _check_built_shapes(graph: FactorGraph, caller: str) -> None:
    """Raise unless the graph's variables have the counts and tangent dimensions, and its
    information matrices the sizes, its structure was built with (static shapes)."""
    st = graph.structure
    for name, n, d in zip(st.names, st.counts, st.dims, strict=True):
        value = graph.variables.get(name) if isinstance(graph.variables, Mapping) else None
        if value is None or count(value) != n or tangent_dim(value) != d:
            got = ("none" if value is None
                   else f"{count(value)} of tangent dimension {tangent_dim(value)}")
            raise ValueError(
                f"{caller}: graph.variables[{name!r}] holds {got}, but the FactorGraph was "
                f"built with {n} of tangent dimension {d} (replaced after construction, e.g. "
                f"by eqx.tree_at?): build a new FactorGraph for other variables")
    for f in graph.factors:
        _check_information(f, graph.variables)


def _stale_indices(caller: str, k: int | None) -> str:
    which = "a factor's" if k is None else f"factor group {k}'s"
    return (f"{caller}: {which} indices differ from those the FactorGraph's structure (the "
            f"sparsity pattern of H) was built from (replaced after construction, e.g. by "
            f"eqx.tree_at?): build a new FactorGraph for new indices")


def _kind(value: Any) -> str:
    """"SE3 of batch shape (n,)", "array of shape (n, d)" or the type's name."""
    if isinstance(value, LieGroup):
        return f"{type(value).__name__} of batch shape {value.shape}"
    if isinstance(value, (jax.Array, np.ndarray)):
        return f"array of shape {value.shape}"
    return type(value).__name__


class GraphLinearization(eqx.Module):
    """A factor graph linearised at one point (:func:`linearize`): whitened residuals and
    Jacobian blocks of every factor group, and the cost."""

    residuals: tuple[Array, ...]  # per factor group: (m, r) whitened (and robustified)
    jacobians: tuple[tuple[Array, ...], ...]  # per group, per slot: (m, r, d_slot)
    cost: Array  # scalar 0.5·Σ ρ(|r̃|²)


def _rho(kernel: Any, r: Array) -> Array:
    """ρ(s) per row, s = |r|² (s itself when kernel is None)."""
    s = jnp.sum(r * r, -1)
    return s if kernel is None else kernel._in_dtype(s.dtype)(s)


def factor_residuals(factor: Factor, variables: Variables) -> Array:
    """Whitened residuals (m, r) of one factor group (no kernel)."""
    vals = [_gather(variables[s], i) for s, i in zip(factor.slots, factor.indices, strict=True)]
    r = jax.vmap(lambda *a: factor.residual(*a[:-1], a[-1]))(*vals, factor.data)
    if factor.sqrt_info is not None:
        r = small_matvec(factor.sqrt_info.astype(r.dtype), r)
    return r


def cost(graph: FactorGraph, variables: Variables) -> Array:
    """0.5 · Σ ρ(rᵀΩr) over all factors."""
    check_variables(graph, variables, "cost(variables)")
    graph = with_checked_kernels(graph)
    return residual_cost(graph, [factor_residuals(f, variables) for f in graph.factors])


def with_checked_kernels(graph: FactorGraph) -> FactorGraph:
    """``graph`` with its kernels' traced parameters (a learned ``Huber(δ)``) checked at
    run time (``eqx.error_if``: δ ≤ 0 would give a negative cost silently); known values
    were checked when the kernels were made, and add nothing here."""
    factors = tuple(f if f.kernel is None else eqx.tree_at(lambda f: f.kernel, f,
                                                            f.kernel._checked())
                    for f in graph.factors)
    return eqx.tree_at(lambda g: g.factors, graph, factors)


def residual_cost(graph: FactorGraph, residuals: Any) -> Array:
    """0.5 · Σ ρ(|r|²) of per-factor whitened residuals (m, r) (:func:`factor_residuals`)."""
    total = 0.0
    for f, r in zip(graph.factors, residuals, strict=True):
        total = total + 0.5 * jnp.sum(_rho(f.kernel, r))
    return jnp.asarray(total)


def zero_linearization(graph: FactorGraph, residuals: Any) -> GraphLinearization:
    """Zeros in the layout of :func:`linearize`, from the per-factor residuals (m, r) or
    their shapes (``jax.eval_shape``): a loop carry's placeholder, without tracing the
    Jacobians."""
    st = graph.structure
    dims = dict(zip(st.names, st.dims, strict=True))
    jac = tuple(
        tuple(jnp.zeros((*r.shape, dims[s]), r.dtype) for s in f.slots)
        for f, r in zip(graph.factors, residuals, strict=True)
    )
    res = tuple(jnp.zeros(r.shape, r.dtype) for r in residuals)
    return GraphLinearization(res, jac, jnp.zeros((), residuals[0].dtype))


def linearize(graph: FactorGraph, variables: Variables) -> GraphLinearization:
    """Residuals and tangent-space Jacobian blocks (fixed variables get zero blocks).

    Robust kernels enter through each factor's corrector (default FastTriggs: residual
    and Jacobian rows scaled by sqrt(ρ'(s)), square-root IRLS); ``cost`` is the robust
    cost 0.5·Σ ρ(s)."""
    check_variables(graph, variables, "linearize(variables)")
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
            zeros = tuple(jnp.zeros((tangent_dim(p),), _dtype(p)) for p in point)

            def res(deltas: tuple[Array, ...]) -> tuple[Array, Array]:
                moved = [_retract(p, d, "retract_linear")
                         for p, d in zip(point, deltas, strict=True)]
                r = f.residual(*moved, data)
                return r, r

            jac, r = jax.jacfwd(res, has_aux=True)(zeros)
            return r, jac

        r, jac = jax.vmap(one)(*vals, f.data)
        if f.sqrt_info is not None:
            s = f.sqrt_info.astype(r.dtype)
            r = small_matvec(s, r)
            jac = tuple(small_matmul(s, j) for j in jac)
        rho = _rho(f.kernel, r)
        if f.kernel is not None:
            sizes = [j.shape[-1] for j in jac]
            r, jcat = f.corrector(f.kernel._in_dtype(r.dtype), r,
                                  jnp.concatenate(jac, axis=-1))
            jac = tuple(jnp.split(jcat, np.cumsum(sizes)[:-1].tolist(), axis=-1))
        jac = tuple(
            j * st.free[type_of[slot]][idx][:, None, None].astype(j.dtype)
            for j, slot, idx in zip(jac, f.slots, f.indices, strict=True)
        )
        jac = stored_together(jac)  # the slots' blocks share most of their computation
        residuals.append(r)
        jacobians.append(jac)
        total = total + 0.5 * jnp.sum(rho)
    return GraphLinearization(tuple(residuals), tuple(jacobians), jnp.asarray(total))


def stored_together(arrays: Sequence[Array]) -> tuple[Array, ...]:
    """``arrays`` unchanged, those of one shape and dtype computed by one fused loop and
    stored (:func:`~jaxpose.lie.series.computed_once`). XLA:CPU otherwise fuses the work
    they share into the consumer of each (a block product, a scatter-add) and repeats it
    there: parking-garage's linearisation and H assembly 8.4 → 5.7 ms with the between
    factor's analytic Jacobians, 15.2 → 7.1 ms with forward-mode ones; its four exact
    Hessian blocks, 19 → 12 ms."""
    out = list(arrays)
    for key in dict.fromkeys((a.shape, a.dtype) for a in arrays):
        same = [i for i, a in enumerate(arrays) if (a.shape, a.dtype) == key]
        if len(same) > 1:
            for i, a in zip(same, computed_once(*(arrays[i] for i in same)), strict=True):
                out[i] = a
    return tuple(out)


def _dtype(p: Any) -> Any:
    return p.dtype


def split(graph: FactorGraph, flat: Array) -> tuple[Array, ...]:
    """Flat tangent (N,) → per-type blocks (n, d)."""
    return split_tangent(graph.structure, flat)


def gradient(graph: FactorGraph, lin: GraphLinearization) -> Array:
    """g = J̃ᵀ r̃ (N,)."""
    st = graph.structure
    type_of = {n: k for k, n in enumerate(st.names)}
    dtype = lin.cost.dtype
    out = [jnp.zeros((c, d), dtype) for c, d in zip(st.counts, st.dims, strict=True)]
    for f, r, jac in zip(graph.factors, lin.residuals, lin.jacobians, strict=True):
        for slot, idx, j in zip(f.slots, f.indices, jac, strict=True):
            k = type_of[slot]
            out[k] = out[k].at[idx].add(small_matvec(j.mT, r))
    return join(out)


def hessian_diagonal(graph: FactorGraph, lin: GraphLinearization) -> Array:
    """diag(H) = column sums of J̃² (N,), without forming any block of H."""
    st = graph.structure
    type_of = {n: k for k, n in enumerate(st.names)}
    dtype = lin.cost.dtype
    out = [jnp.zeros((c, d), dtype) for c, d in zip(st.counts, st.dims, strict=True)]
    for f, jac in zip(graph.factors, lin.jacobians, strict=True):
        for slot, idx, j in zip(f.slots, f.indices, jac, strict=True):
            k = type_of[slot]
            out[k] = out[k].at[idx].add(jnp.sum(j * j, axis=1))
    return join(out)


def block_diagonal(graph: FactorGraph, lin: GraphLinearization) -> tuple[Array, ...]:
    """Diagonal blocks of H per type: (n, d, d)."""
    st = graph.structure
    type_of = {n: k for k, n in enumerate(st.names)}
    dtype = lin.cost.dtype
    out = [jnp.zeros((c, d, d), dtype) for c, d in zip(st.counts, st.dims, strict=True)]
    for f, jac in zip(graph.factors, lin.jacobians, strict=True):
        for slot, idx, j in zip(f.slots, f.indices, jac, strict=True):
            k = type_of[slot]
            out[k] = out[k].at[idx].add(small_matmul(j.mT, j))
    return tuple(out)


def hessian_vector(graph: FactorGraph, lin: GraphLinearization, v: Array) -> Array:
    """H v = J̃ᵀ(J̃ v) without forming H (N,)."""
    st = graph.structure
    type_of = {n: k for k, n in enumerate(st.names)}
    vb = split(graph, v)
    out = [jnp.zeros_like(b) for b in vb]
    for f, jac in zip(graph.factors, lin.jacobians, strict=True):
        u = 0.0
        for slot, idx, j in zip(f.slots, f.indices, jac, strict=True):
            u = u + small_matvec(j, vb[type_of[slot]][idx])
        for slot, idx, j in zip(f.slots, f.indices, jac, strict=True):
            k = type_of[slot]
            out[k] = out[k].at[idx].add(small_matvec(j.mT, u))
    return join(out)


def assemble_blocks(
    graph: FactorGraph, pair_block: Any, dtype: Any
) -> list[Array]:
    """A matrix with H's block pattern from per-factor blocks: ``pair_block(k, s, t)``
    gives factor group k's (m, d_s, d_t) blocks of slot pair (s, t). Returns the class
    arrays of ``graph.structure.pattern``."""
    contributions = [contribution for k in range(len(graph.factors))
                     for contribution in group_blocks(graph, k, pair_block)]
    return scatter_blocks(graph.structure.pattern.zeros(dtype), contributions)


def group_blocks(graph: FactorGraph, k: int, pair_block: Any,
                 take: Any = None) -> list[tuple[int, Array, Array]]:
    """Factor group k's ``(class, block index, pair_block(k, s, t))`` for every slot pair
    (:func:`~jaxpose.graph._pattern.scatter_blocks`'s contributions); ``take`` selects the
    rows of a chunk from the per-factor block indices (default: all rows)."""
    st = graph.structure
    take = (lambda a: a) if take is None else take
    return [(c, take(idx), pair_block(k, s, t)) for (s, t), c, idx in
            zip(slot_pairs(len(graph.factors[k].slots)), st.block_class[k], st.block_index[k],
                strict=True)]


def normal_dtype(dtype: Any) -> Any:
    """The dtype H = J̃ᵀJ̃ is formed and factorised in for a problem of ``dtype``: float64
    whenever JAX has it (x64 enabled), else ``dtype``.

    A float32 JᵀJ is indefinite once H's condition number passes 1/eps ≈ 1e7 (long
    pose-graph chains such as manhattan or parking-garage, BA's reduced camera systems),
    so LM's damped Cholesky fails and its steps stall under heavy damping. The same
    float32 Jacobian's product formed in float64 stays positive semi-definite to that
    condition. Residuals, Jacobians, the gradient and the step stay in ``dtype``."""
    return jnp.promote_types(dtype, jax.dtypes.canonicalize_dtype(jnp.float64))


def jtj_blocks(lin: GraphLinearization, dtype: Any) -> Any:
    """The Gauss–Newton blocks ``block(k, s, t)`` = J_sᵀJ_t (m, d_s, d_t) of factor group
    k's slots s and t, formed in ``dtype`` (:func:`normal_dtype`); a block (t, s) asked for
    after (s, t) is its transpose."""
    cache: dict[tuple[int, int, int], Array] = {}

    def jtj(k: int, s: int, t: int) -> Array:
        if (k, t, s) in cache:
            return cache[k, t, s].mT
        jac = lin.jacobians[k]
        cache[k, s, t] = small_matmul(jac[s].astype(dtype).mT, jac[t].astype(dtype))
        return cache[k, s, t]

    return jtj


def hessian_blocks(graph: FactorGraph, lin: GraphLinearization) -> list[Array]:
    """H = J̃ᵀJ̃ as class arrays of ``graph.structure.pattern``, in
    :func:`normal_dtype`."""
    dtype = normal_dtype(lin.cost.dtype)
    return assemble_blocks(graph, jtj_blocks(lin, dtype), dtype)


def csr_values(graph: FactorGraph, lin: GraphLinearization) -> Array:
    """Values of H in the precomputed CSR pattern (nnz,), in :func:`normal_dtype`."""
    return graph.structure.pattern.csr(hessian_blocks(graph, lin))


def free_flat(graph: FactorGraph, dtype: Any) -> Array:
    """(N,) 1 for the tangent coordinates of free variables, 0 for fixed ones."""
    st = graph.structure
    return jnp.concatenate(
        [jnp.repeat(jnp.asarray(f), d) for f, d in zip(st.free, st.dims, strict=True)]
    ).astype(dtype)


def retract_all(graph: FactorGraph, variables: Variables, step: Array,
                method: str = "retract") -> Variables:
    """Apply a flat tangent step to every variable type (fixed ones have zero steps);
    ``method`` as in :func:`_retract`."""
    blocks = split(graph, step)
    # each variable keeps its dtype (float64 data promote the step of float32 variables)
    return {
        name: _retract(
            variables[name],
            (blocks[k] * graph.structure.free[k][:, None]).astype(
                jax.tree.leaves(variables[name])[0].dtype),
            method,
        )
        for k, name in enumerate(graph.structure.names)
    }
