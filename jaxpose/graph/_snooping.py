"""Outlier test statistics of a solved factor graph (Baarda's data snooping).

At a solution X* of ``min ½ Σ |r̃_k|²`` (r̃ the whitened residual, J̃ its Jacobian in the
tangent chart, H = J̃ᵀJ̃, Σ = H⁻¹ with fixed variables held), factor k's *deletion
statistic* is

    T_k = r̃_kᵀ (I − L_k)⁻¹ r̃_k,   L_k = J̃_k Σ_k J̃_kᵀ,

Σ_k the joint marginal of the factor's variables. In the linearised model, T_k is what
removing factor k and re-solving takes off the total cost ``Σ |r̃|²``: the others' part
drops by ``T_k − |r̃_k|²``, and the factor's own residual after the re-solve, whitened by
the covariance of that prediction, has squared norm T_k (the deleted, studentised
residual; its plain squared norm ``r̃_kᵀ(I − L_k)⁻²r̃_k`` is larger still). For an inlier
with Gaussian noise T_k is χ² with the residual's dimension as degrees of freedom (Baarda's
data snooping, 1968, in its form for a group of observations), so T_k > χ²₀.₉₉ flags an
outlier; unlike the residual itself it also flags a wrong factor that the others cannot
contradict much (high leverage: the solution bent to fit it). ``I − L_k`` (the redundancy) is
singular for a factor that alone constrains some direction (a bridge of the graph):
removing it would leave that direction free and the test cannot see it; T_k is then NaN.

A factor left out of the solve (``kept`` in :func:`statistics`) gets the mirror image,
its *addition statistic* (the innovation test of a Kalman update)

    T_k = r̄_kᵀ (I + L̄_k)⁻¹ r̄_k,   L̄_k = J̄_k Σ_k J̄_kᵀ,

r̄, J̄ its whitened residual and Jacobian at X*, Σ from the kept factors: what adding
factor k and re-solving adds to ``Σ s`` in the linearised model (``I + L̄_k`` is the
covariance of the factor's prediction error; always invertible).

Used by :func:`jaxpose.graph.gnc`'s local search (``max_deletions``,
``max_readmissions``).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._precision import full_precision
from ._marginals import _Plan, inverse_entries
from ._problem import FactorGraph, check_structure, check_variables, linearize, with_checked_kernels
from ._solve import GraphLinearSolver

Array = jax.Array
METHODS = ("auto", "dense", "sparse")
REDUNDANCY_MIN = 1e-9
"""Smallest eigenvalue of ``I − L_k`` for which T_k is computed (NaN below); in lower
precision at least 1000 ε of the dtype (float32: 1.2e-4)."""


def plan(graph: FactorGraph, method: str, caller: str = "deletion_statistics") -> _Plan:
    """Every factor's joint block of H⁻¹ over its variables, one (m, D, D) request per
    factor group (D the sum of its slots' tangent dimensions); needs concrete factor
    indices (built on the host, static in the compiled program)."""
    if method not in METHODS:
        raise ValueError(f"{caller}(method={method!r}): expected one of {METHODS}")
    if graph.structure.schur is not None:
        raise ValueError(
            f"{caller}(graph): graphs built with eliminate= are not supported; build the "
            "same factors without eliminate")
    if method == "auto":
        method = "dense" if graph.size <= GraphLinearSolver().dense_max else "sparse"
    try:
        indices = [[np.asarray(i, np.int64) for i in f.indices] for f in graph.factors]
    except jax.errors.TracerArrayConversionError:
        raise ValueError(
            f"{caller}(graph): the factor indices must be concrete (call it outside "
            "jax.jit, or close over the graph instead of passing it as an argument)"
        ) from None
    st = graph.structure
    type_of = {n: k for k, n in enumerate(st.names)}
    base = dict(zip(st.names, st.offsets[:-1], strict=True))
    rows, cols, shapes = [], [], []
    for f, idx in zip(graph.factors, indices, strict=True):
        scalars = np.concatenate(
            [base[s] + i[:, None] * st.dims[type_of[s]] + np.arange(st.dims[type_of[s]])[None, :]
             for s, i in zip(f.slots, idx, strict=True)], axis=1)  # (m, D)
        m, dim = scalars.shape
        rows.append(np.repeat(scalars[:, :, None], dim, 2).reshape(-1))
        cols.append(np.repeat(scalars[:, None, :], dim, 1).reshape(-1))
        shapes.append((m, dim, dim))
    return _Plan(method, tuple(st.names), np.concatenate(rows), np.concatenate(cols),
                 tuple(shapes), 0.0, 0, None)


def deletion_statistics(graph: FactorGraph, values: Any = None, *,
                        method: str = "auto", kept: Any = None) -> tuple[Array, ...]:
    """Per factor group, (m,) deletion statistics ``T_k`` at ``values`` (module docstring);
    with ``kept``, the addition statistics of the factors left out.

    Args:
        graph: a :class:`~jaxpose.graph.FactorGraph` without Schur elimination; robust
            kernels enter through their correctors (the solver's linearisation).
        values: variables to linearise at (a solution of ``graph``; default
            ``graph.variables``). At a point that is not a solution, T_k is not the
            deleted residual.
        method: how Σ's blocks are computed: ``"dense"`` (Cholesky; jit, vmap, grad),
            ``"sparse"`` (CHOLMOD's selected inversion on the host; jit, sequential vmap),
            ``"auto"`` (dense up to the solver's ``dense_max`` dimensions).
        kept: optional, per factor group a (m,) bool array (a bare array for a one-group
            graph): the factors of the solve ``values`` solves. A factor left out gets
            its addition statistic (what adding it and re-solving adds to ``Σ s``);
            default: every factor kept.

    Returns:
        One (m,) array per factor group: ``T_k`` (≥ |r̃_k|² ≥ 0 for a kept factor, in
        [0, |r̃_k|²] for one left out; 0 for a factor with zero information, NaN where
        ``I − L_k`` has an eigenvalue below :data:`REDUNDANCY_MIN`: the factor alone
        constrains a direction). A singular H (a
        free gauge) gives non-finite values.
    """
    if not isinstance(graph, FactorGraph):
        raise TypeError(
            f"deletion_statistics(graph): expected a FactorGraph, got {type(graph).__name__}")
    graph = check_structure(graph, "deletion_statistics")
    values = graph.variables if values is None else values
    check_variables(graph, values, "deletion_statistics(values)")
    if kept is not None:
        kept = (kept,) if len(graph.factors) == 1 and not isinstance(kept, (tuple, list)) \
            else tuple(kept)
        if len(kept) != len(graph.factors):
            raise ValueError(f"deletion_statistics(kept): expected {len(graph.factors)} arrays "
                             f"(one per factor group), got {len(kept)}")
        kept = tuple(jnp.asarray(k) for k in kept)
        for g, (k, f) in enumerate(zip(kept, graph.factors, strict=True)):
            if k.dtype != bool or k.shape != (f.count,):
                raise ValueError(f"deletion_statistics(kept[{g}]): expected a bool array of "
                                 f"shape ({f.count},), got {k.dtype} {k.shape}")
    return statistics(with_checked_kernels(graph), values, plan(graph, method), kept)


def _masked(lin: Any, kept: tuple[Array, ...]) -> Any:
    """``lin`` with the rows of the factors not ``kept`` zeroed (the solve without them)."""
    mask = [k.astype(r.dtype) for k, r in zip(kept, lin.residuals, strict=True)]
    return eqx.tree_at(
        lambda t: (t.residuals, t.jacobians), lin,
        (tuple(r * m[:, None] for r, m in zip(lin.residuals, mask, strict=True)),
         tuple(tuple(j * m[:, None, None] for j in jac)
               for jac, m in zip(lin.jacobians, mask, strict=True))))


@full_precision
def statistics(graph: FactorGraph, values: Any, blocks_plan: _Plan,
               kept: tuple[Array, ...] | None = None) -> tuple[Array, ...]:
    """:func:`deletion_statistics` with the covariance blocks' :func:`plan` made
    beforehand (traceable: ``graph`` may be traced, the plan is static). ``kept``: per
    factor group, (m,) bools, the factors in the solve (default: all); the others get
    their addition statistic (module docstring), Σ comes from the kept ones."""
    lin = linearize(graph, values)
    solved = lin if kept is None else _masked(lin, kept)
    if kept is None:
        kept = tuple(jnp.ones(r.shape[:1], bool) for r in lin.residuals)
    blocks = inverse_entries(graph, solved, blocks_plan, "deletion_statistics",
                             "method='dense' to differentiate")
    out = []
    for r, jac, cov, k in zip(lin.residuals, lin.jacobians, blocks, kept, strict=True):
        j = jnp.concatenate(jac, axis=-1)  # (m, rdim, D)
        sign = jnp.where(k, -1.0, 1.0).astype(r.dtype)[:, None, None]
        spread = jnp.eye(r.shape[-1], dtype=r.dtype) + sign * (j @ cov @ jnp.swapaxes(j, -1, -2))
        spread = 0.5 * (spread + jnp.swapaxes(spread, -1, -2))
        lowest = jnp.linalg.eigvalsh(spread)[..., 0]
        ok = lowest > max(REDUNDANCY_MIN, 1000 * float(jnp.finfo(r.dtype).eps))
        safe = jnp.where(ok[:, None, None], spread, jnp.eye(r.shape[-1], dtype=r.dtype))
        t = jnp.sum(r * jnp.linalg.solve(safe, r[..., None])[..., 0], -1)
        out.append(jnp.where(ok, t, jnp.nan))
    return tuple(out)
