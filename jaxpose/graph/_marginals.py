"""Marginal covariances of a solved factor graph (GTSAM's ``Marginals``).

At the solution X*, the Gauss–Newton (Laplace) approximation of the posterior is Gaussian
in the tangent chart at X*: X = X* ⊕ δ = X*·Exp(δ) (right perturbation, arrays: X* + δ),
δ ~ N(0, H⁻¹) with H = J̃ᵀJ̃ the whitened Gauss–Newton matrix (robust kernels enter
through their correctors, as in the solver). A variable's *marginal covariance* is its
diagonal block of H⁻¹; the *joint marginal* of two variables is the 2×2 block matrix of
their blocks. δ uses jaxpose's tangent layout per variable (se3 ``[ρ, φ]``, translation
first; se2 ``[ρx, ρy, θ]``; arrays: their own axes).

Relation to GTSAM: Pose3's tangent is ``[ω, v]`` (rotation first), also a right
perturbation (``retract`` = X·Exp(ξ) with the default expmap chart), so
``Σ_gtsam = P Σ_jaxpose Pᵀ`` with P swapping the two 3-blocks (:func:`se3_to_gtsam`);
Pose2 ``[x, y, θ]`` is the same as se2. Fixed variables (the gauge, ``FactorGraph(fixed=)``)
are held exactly: the covariance of the free variables is conditioned on them (the free
block of H inverted) and their own blocks are zero. GTSAM cannot hold a variable fixed; the
same covariances come from a prior with a constrained noise model (``noiseModel.
Constrained``, eliminated with ``Marginals.Factorization.QR``) or, approximately, a tight
prior.

Methods (``method=``): ``"dense"`` (Cholesky of the dense H; jit, vmap and grad),
``"sparse"`` (CHOLMOD on the host through a callback; selected inversion of the
supernodal factor, :mod:`jaxpose.graph._selinv`; jit, sequential vmap, no grad),
``"pcg"`` (block-Jacobi preconditioned CG, one solve per requested column; any device,
jit, vmap, grad), ``"schur"`` (graphs built with ``eliminate=``: the kept variables'
marginals are blocks of the inverse of the reduced matrix S = U − W V⁻¹ Wᵀ, factorised
like ``"sparse"``), ``"auto"`` (``"schur"`` when the graph eliminates a type and only
kept types are requested, else ``"dense"`` up to 600 tangent dimensions, else
``"sparse"``). Differentiating ``"sparse"`` or ``"schur"`` (or ``"auto"`` when it picks
them) raises; ``"dense"`` and ``"pcg"`` differentiate.
"""

from __future__ import annotations

import operator
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count
from .._precision import full_precision
from ..optim._stopping import check_tolerance
from . import _linear as linear
from . import _selinv as selinv
from ._implicit import open_gauge
from ._problem import (
    FactorGraph,
    check_structure,
    check_variables,
    csr_values,
    hessian_vector,
    linearize,
    normal_dtype,
    with_checked_kernels,
)
from ._solve import (
    GraphLinearSolver,
    GraphSolution,
    damped_block_jacobi,
)

Array = jax.Array
METHODS = ("auto", "dense", "sparse", "pcg", "schur")
FLOAT32_CG_RTOL = 1e-5
"""Smallest ``cg_rtol`` used in float32 (the backward's float32 tolerance): the default
1e-12 is below float32's resolution, so its CG could never be shown to converge."""


class Marginals(eqx.Module):
    """Result of :func:`marginals`.

    ``covariances[name]``: (k, d, d) marginal covariances of the requested variables of
    type ``name`` (in the order of ``indices[name]``, (k,)); ``joint``: for ``pairs``
    given as an (P, 2) index array over one type, an array (P, 2d, 2d) with blocks
    ``[[Σ_aa, Σ_ab], [Σ_ba, Σ_bb]]``; for pairs given as ``((type_a, i), (type_b, j))``,
    a tuple of (d_a + d_b, d_a + d_b) arrays; None without pairs. Chart and conventions:
    :mod:`jaxpose.graph.marginals`."""

    covariances: dict[str, Array]
    indices: dict[str, Array]
    joint: Any = None


def _selection(graph: FactorGraph, variables: Any, default: Sequence[str]) -> dict[str, np.ndarray]:
    st = graph.structure
    counts = dict(zip(st.names, st.counts, strict=True))
    if variables is None:
        variables = list(default)
    if isinstance(variables, str):
        variables = [variables]
    if not isinstance(variables, Mapping):
        variables = {name: None for name in variables}
    out = {}
    for name, idx in variables.items():
        if name not in counts:
            raise KeyError(
                f"marginals(variables): unknown variable type {name!r}; expected one of "
                f"{list(st.names)}"
            )
        if idx is None:
            idx = np.arange(counts[name])
        idx = np.asarray(idx)
        if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
            raise ValueError(
                f"marginals(variables[{name!r}]): expected a 1-D integer index array, got "
                f"shape {idx.shape} dtype {idx.dtype}"
            )
        if idx.size and (idx.min() < 0 or idx.max() >= counts[name]):
            raise IndexError(
                f"marginals(variables[{name!r}]): index out of range for {counts[name]} "
                f"variables"
            )
        out[name] = idx.astype(np.int64)
    return out


def _pairs(graph: FactorGraph, pairs: Any, single: str | None):
    """((type_a, i_a, type_b, i_b) list, stacked?)."""
    if pairs is None:
        return [], False
    st = graph.structure
    counts = dict(zip(st.names, st.counts, strict=True))
    arr = None
    try:
        arr = np.asarray(pairs)
    except ValueError:
        arr = None
    if arr is not None and np.issubdtype(arr.dtype, np.integer):
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise ValueError(f"marginals(pairs): expected an (P, 2) index array, got shape "
                             f"{arr.shape}")
        if single is None:
            raise ValueError(
                "marginals(pairs): an (P, 2) index array needs one variable type; name it "
                "with variables=TYPE or give pairs as ((type_a, i), (type_b, j))"
            )
        out = [(single, int(a), single, int(b)) for a, b in arr]
        stacked = True
    else:
        out = []
        for k, p in enumerate(pairs):
            try:
                (ta, ia), (tb, ib) = p
                ia, ib = operator.index(ia), operator.index(ib)  # 1.7 is not an index
            except (TypeError, ValueError):
                raise ValueError(
                    f"marginals(pairs[{k}]): expected ((type_a, i), (type_b, j)) with integer "
                    f"indices i, j, got {p!r}"
                ) from None
            out.append((ta, ia, tb, ib))
        stacked = False
    for k, (ta, ia, tb, ib) in enumerate(out):
        for t, i in ((ta, ia), (tb, ib)):
            if t not in counts:
                raise KeyError(f"marginals(pairs[{k}]): unknown variable type {t!r}")
            if not 0 <= i < counts[t]:
                raise IndexError(
                    f"marginals(pairs[{k}]): index {i} out of range for {counts[t]} {t!r} "
                    f"variables"
                )
    return out, stacked


def _block_entries(offsets: Sequence[int], dims: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Row/column indices of the square blocks over the given scalar slices, (k, D, D)."""
    rows, cols = [], []
    for o, d in zip(offsets, dims, strict=True):
        r = np.arange(o, o + d)
        rows.append(np.repeat(r[:, None], d, 1))
        cols.append(np.repeat(r[None, :], d, 0))
    return np.stack(rows), np.stack(cols)


def se3_to_gtsam(cov: Any) -> np.ndarray:
    """Map (…, 6, 6) covariances from jaxpose's se3 chart ``[ρ, φ]`` to GTSAM Pose3's
    ``[ω, v]`` (swap the 3-blocks; both charts are right perturbations)."""
    p = np.r_[3:6, 0:3]
    cov = np.asarray(cov)
    return cov[..., p, :][..., :, p]


def marginals(
    graph: FactorGraph,
    solution: GraphSolution | Mapping[str, Any] | None = None,
    variables: Any = None,
    *,
    pairs: Any = None,
    method: str = "auto",
    cg_rtol: float = 1e-12,
    cg_max_iters: int = 2000,
    batch_size: int | None = 64,
) -> Marginals:
    """Marginal (and joint) covariances of a factor graph's variables at a solution.

    Args:
        graph: the :class:`~jaxpose.graph.FactorGraph` (the problem that was solved).
        solution: the :func:`~jaxpose.graph.solve` result (or a variables mapping) to
            linearise at; default: ``graph.variables``.
        variables: which variables: a type name (all of that type), a list of type names,
            or ``{name: indices}``; default: every type (every kept type for a graph with
            ``eliminate=``).
        pairs: joint marginals: an (P, 2) integer array of index pairs of the single type
            named in ``variables``, or a sequence of ``((type_a, i), (type_b, j))``.
        method: ``"auto"``, ``"dense"``, ``"sparse"``, ``"pcg"`` or ``"schur"`` (module
            docstring).
        cg_rtol, cg_max_iters: tolerance and budget of each CG solve (``"pcg"``; in
            float32 at least :data:`FLOAT32_CG_RTOL`).
        batch_size: columns solved at once by ``"pcg"`` (``lax.map`` batches).

    Returns:
        :class:`Marginals`: covariances in the tangent chart at the solution (right
        perturbation, jaxpose's tangent layout; :func:`se3_to_gtsam` maps se3 blocks to
        GTSAM's order); fixed variables have zero blocks. An open gauge that the graph
        shows (between factors only with no pose fixed, BAL reprojections only with
        fewer than two cameras fixed) raises ``ValueError``; another singular H (an
        unobserved direction) gives values that are not covariances, usually non-finite;
        with ``"pcg"`` a column whose CG does not reach ``cg_rtol`` (checked on its true
        residual) within ``cg_max_iters`` raises instead of returning an inexact
        covariance.

    The selection is checked eagerly; the computation is compiled (``eqx.filter_jit``), so
    a repeated call on a graph of the same structure with new values reuses the program.
    """
    if method not in METHODS:
        raise ValueError(f"marginals(method={method!r}): expected one of {METHODS}")
    check_tolerance(cg_rtol, "marginals(cg_rtol)", positive=True)
    cg_max_iters = check_count(cg_max_iters, "marginals(cg_max_iters)")
    if batch_size is not None:
        batch_size = check_count(batch_size, "marginals(batch_size)")
    if not isinstance(graph, FactorGraph):
        raise TypeError(f"marginals(graph): expected a FactorGraph, got {type(graph).__name__}")
    if solution is None:
        values = graph.variables
    elif isinstance(solution, GraphSolution):
        values = solution.variables
    elif isinstance(solution, Mapping):
        values = dict(solution)
    else:
        raise TypeError(
            f"marginals(solution): expected a GraphSolution, a variables mapping or None, got "
            f"{type(solution).__name__}"
        )
    graph = check_structure(graph, "marginals")
    check_variables(graph, values, "marginals(solution)")
    gauge = open_gauge(graph)
    if gauge is not None:  # H is singular: a factorisation may still "succeed" on rounding
        raise ValueError(f"marginals: the covariances are undefined: {gauge[0]} (a gauge "
                         f"freedom), so H is singular. To compute them, {gauge[1]}.")
    graph = with_checked_kernels(graph)
    st = graph.structure
    schur = st.schur
    kept_names = (st.names if schur is None
                  else tuple(n for k, n in enumerate(st.names) if k != schur.eliminated))
    sel = _selection(graph, variables, kept_names)
    single = next(iter(sel)) if len(sel) == 1 else (st.names[0] if len(st.names) == 1
                                                   else None)
    pair_list, stacked = _pairs(graph, pairs, single)
    used = set(sel) | {p[0] for p in pair_list} | {p[2] for p in pair_list}
    if method == "auto":
        if schur is not None and used <= set(kept_names):
            method = "schur"
        else:
            method = "dense" if graph.size <= GraphLinearSolver().dense_max else "sparse"
    if method == "schur":
        if schur is None:
            raise ValueError(
                "marginals(method='schur'): the graph eliminates no variable type; build it "
                "with FactorGraph(..., eliminate=TYPE_NAME)"
            )
        if not used <= set(kept_names):
            raise ValueError(
                f"marginals(method='schur'): {sorted(used - set(kept_names))} is the eliminated "
                f"type; use method='sparse' or 'dense' for its marginals"
            )
        layout_names = kept_names
    else:
        layout_names = st.names

    # scalar offsets of every variable in the layout of the matrix that is inverted
    type_of = {n: k for k, n in enumerate(st.names)}
    base, off = {}, 0
    for n in layout_names:
        base[n] = off
        off += st.counts[type_of[n]] * st.dims[type_of[n]]

    def where(name: str, i: Any) -> Any:
        return base[name] + np.asarray(i) * st.dims[type_of[name]]

    requests = []  # (rows, cols) index arrays, in the order of the outputs
    for name, idx in sel.items():
        d = st.dims[type_of[name]]
        requests.append(_block_entries(where(name, idx), [d] * idx.size))
    for ta, ia, tb, ib in pair_list:
        da, db = st.dims[type_of[ta]], st.dims[type_of[tb]]
        r = np.r_[where(ta, ia) + np.arange(da), where(tb, ib) + np.arange(db)]
        requests.append((np.repeat(r[:, None], r.size, 1)[None],
                         np.repeat(r[None, :], r.size, 0)[None]))
    flat_i = np.concatenate([r.reshape(-1) for r, _ in requests]) if requests else np.zeros(
        0, np.int64)
    flat_j = np.concatenate([c.reshape(-1) for _, c in requests]) if requests else np.zeros(
        0, np.int64)

    plan = _Plan(method, layout_names, flat_i, flat_j, tuple(r.shape for r, _ in requests),
                 cg_rtol, cg_max_iters, batch_size)
    out = _entries(graph, values, plan)
    covs = {name: out[k] for k, name in enumerate(sel)}
    joint_list = out[len(sel):]
    if not pair_list:
        joint = None
    elif stacked:
        joint = jnp.concatenate(joint_list, 0)
    else:
        joint = tuple(j[0] for j in joint_list)
    return Marginals(
        covariances=covs,
        indices={n: jnp.asarray(i, jnp.int32) for n, i in sel.items()},
        joint=joint,
    )


class _Plan:
    """What :func:`_entries` computes, fixed before compilation (static under
    ``eqx.filter_jit``, so equal plans share one compiled program): the method, the
    layout of the inverted matrix, the requested entries (flat row/column indices) and
    the shape each request is cut into."""

    def __init__(self, method: str, layout_names: tuple[str, ...], flat_i: np.ndarray,
                 flat_j: np.ndarray, shapes: tuple[tuple[int, ...], ...], cg_rtol: float,
                 cg_max_iters: int, batch_size: int | None):
        self.method, self.layout_names, self.shapes = method, tuple(layout_names), shapes
        self.flat_i, self.flat_j = flat_i.astype(np.int64), flat_j.astype(np.int64)
        self.cg = (cg_rtol, cg_max_iters, batch_size)
        self._key = (method, self.layout_names, shapes, self.flat_i.tobytes(),
                     self.flat_j.tobytes(), self.cg)

    def __hash__(self) -> int:
        return hash(self._key)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Plan) and self._key == other._key


@eqx.filter_jit
@full_precision
def _entries(graph: FactorGraph, values: Any, plan: _Plan) -> list[Array]:
    """The requested entries of H⁻¹ at ``values``, one array per request (compiled: a
    repeated call with new values of the same structure reuses the program)."""
    return inverse_entries(graph, linearize(graph, values), plan)


def inverse_entries(graph: FactorGraph, lin: Any, plan: _Plan, caller: str = "marginals",
                    instead: str = "method='dense' or method='pcg' to differentiate "
                                   "marginal covariances") -> list[Array]:
    """:func:`_entries` at a linearisation ``lin`` of ``graph`` (traceable). A host method
    differentiated raises naming ``caller`` and what to use ``instead``."""
    st = graph.structure
    type_of = {n: k for k, n in enumerate(st.names)}
    flat_i, flat_j = plan.flat_i, plan.flat_j
    # the factorised methods invert H in normal_dtype (float64 for a float32 problem when
    # x64 is on); CG works in the problem's dtype; the entries come back in it
    dtype = lin.cost.dtype if plan.method == "pcg" else normal_dtype(lin.cost.dtype)
    free = jnp.concatenate(
        [jnp.repeat(f, d) for f, d in zip(st.free, st.dims, strict=True)]).astype(dtype)
    if plan.method == "schur":
        data, _, _, _ = _reduced(graph, lin, free)
        free_l = jnp.concatenate([jnp.repeat(st.free[type_of[n]], st.dims[type_of[n]])
                                  for n in plan.layout_names]).astype(dtype)
        pattern = st.schur.pattern
        vals = _sparse_entries(data, pattern.indices, pattern.indptr, flat_i, flat_j,
                               plan.method, caller, instead)
    else:
        free_l = free
        if plan.method == "pcg":
            vals = _pcg_entries(graph, lin, free, flat_i, flat_j, *plan.cg)
        else:
            data = csr_values(graph, lin).at[st.diag_pos].add(1.0 - free)
            if plan.method == "sparse":
                vals = _sparse_entries(data, st.csr_indices, st.csr_indptr, flat_i, flat_j,
                                       plan.method, caller, instead)
            else:
                vals = _dense_entries(data, st.csr_indices, st.csr_indptr, flat_i, flat_j)
    vals = (vals * free_l[flat_i] * free_l[flat_j]).astype(lin.cost.dtype)
    out, start = [], 0
    for shape in plan.shapes:
        size = int(np.prod(shape))
        out.append(vals[start : start + size].reshape(shape))
        start += size
    return out


def _reduced(graph: FactorGraph, lin: Any, free: Array) -> Any:
    from ._problem import jtj_blocks
    from ._schur import reduced_system, schur_parts

    return reduced_system(graph, schur_parts(graph, jtj_blocks(lin, free.dtype), free.dtype),
                          1.0 - free)


def _dense_entries(data: Array, indices: Array, indptr: Array, i: np.ndarray,
                   j: np.ndarray) -> Array:
    n = indptr.shape[0] - 1
    dense = linear.densify(data, linear.dense_index(indices, indptr, n), n)
    cols, inv = np.unique(j, return_inverse=True)
    rhs = jnp.zeros((n, cols.size), data.dtype).at[cols, np.arange(cols.size)].set(1.0)
    return linear.cholesky_solve(dense, rhs)[i, inv]


def _sparse_entries(data: Array, indices: Array, indptr: Array, i: np.ndarray,
                    j: np.ndarray, method: str, caller: str, instead: str) -> Array:
    """Entries by selected inversion on the host (``method`` "sparse" or "schur"). The
    callback has no derivative: differentiating raises, naming ``caller`` and what to use
    ``instead``."""
    data = eqxi.nondifferentiable(data, msg=(
        f"{caller}(method={method!r}) is not differentiable (the factorisation and "
        f"selected inversion run on the host); use {instead}"))

    def host(d: Any, ind: Any, ptr: Any) -> np.ndarray:
        return selinv.inverse_entries(np.asarray(d, np.float64), ind, ptr, i, j).astype(
            d.dtype)

    out = jax.ShapeDtypeStruct((i.size,), data.dtype)
    return jax.pure_callback(host, out, data, indices, indptr, vmap_method="sequential")


def _pcg_entries(graph: FactorGraph, lin: Any, free: Array, i: np.ndarray, j: np.ndarray,
                 rtol: float, max_iters: int, batch_size: int | None) -> Array:
    add = 1.0 - free
    precond = damped_block_jacobi(graph, lin, add)
    n = graph.size
    cols, inv = np.unique(j, return_inverse=True)

    if jnp.dtype(add.dtype).itemsize < 8:  # float32 cannot reach the float64 default
        rtol = max(rtol, FLOAT32_CG_RTOL)
    inner = linear.pcg_spd(precond, rtol, max_iters)  # NaN where rtol is not reached

    def column(c: Array) -> Array:
        e = jnp.zeros((n,), add.dtype).at[c].set(1.0)
        # custom_linear_solve: derivatives by the linear solve's own rule (the CG, whose
        # preconditioner lineax cannot differentiate, is never differentiated itself)
        return jax.lax.custom_linear_solve(
            lambda v: hessian_vector(graph, lin, v) + add * v, e, inner, symmetric=True)

    solved = jax.lax.map(column, jnp.asarray(cols), batch_size=batch_size)  # (k, n)
    return eqx.error_if(
        solved[inv, i], ~jnp.all(jnp.isfinite(solved)),
        f"marginals(method='pcg'): conjugate gradients did not reach cg_rtol={rtol} within "
        f"cg_max_iters={max_iters} iterations for some columns (H ill-conditioned for its "
        "block-Jacobi preconditioner, or singular: no gauge fixed); raise cg_max_iters, or "
        "use method='sparse' or 'dense'")
