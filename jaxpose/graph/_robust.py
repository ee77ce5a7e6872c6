"""Graduated non-convexity (GNC) for outlier-robust factor graphs.

Yang, Antonante, Tzoumas, Carlone, "Graduated Non-Convexity for Robust Spatial
Perception: From Non-Minimal Solvers to Global Outlier Rejection", RA-L 2020.

Each factor k has a squared whitened residual ``s_k = r_kᵀ Ω_k r_k`` and an inlier
threshold ``c̄²_k`` on s (default: the χ² quantile at probability 0.99 for the residual
dimension, i.e. GTSAM's ``setInlierCostThresholdsAtProbability(0.99)``; GTSAM's
``barcSq`` is half of ours because its factor error is ``0.5·s``). The robust cost is
``0.5·Σ ρ(s_k)`` with

* TLS (truncated least squares): ``ρ(s) = min(s, c̄²)``;
* GM (Geman–McClure): ``ρ(s) = c̄² s / (c̄² + s)``.

GNC minimises a sequence of surrogates ``ρ_μ`` by alternating (Black–Rangarajan duality)

1. a weighted least-squares solve ``min_x 0.5·Σ w_k s_k(x)`` (inner solver: the sparse
   :func:`jaxpose.graph.solve` or the dense :func:`jaxpose.optim.least_squares`),
2. the closed-form weight update at fixed x (paper eqs. 12 and 14):

   * TLS: ``w = 1`` if ``s ≤ μ/(μ+1)·c̄²``, ``w = 0`` if ``s ≥ (μ+1)/μ·c̄²``, else
     ``w = c̄·√(μ(μ+1)/s) − μ``;
   * GM: ``w = (μ c̄² / (s + μ c̄²))²``,

3. a control-parameter update: TLS ``μ ← μ·mu_step`` (from ``μ₀ = c̄²/(2 s_max − c̄²)``,
   convex for small μ), GM ``μ ← max(1, μ/mu_step)`` (from ``μ₀ = 2 s_max/c̄²``).

It stops (GTSAM's rules) when the weights are binary within ``weights_tol`` (TLS), when
μ reaches 1 (GM), when the weighted cost changes by less than ``cost_rtol`` relative (GM;
TLS only with binary weights: unlike GTSAM, a plateau with a fractional weight goes on,
as one factor's weight can move a large graph's cost by less than ``cost_rtol``), or
after ``max_iterations`` outer iterations. Known inliers (e.g. the odometry edges of a
pose graph) keep weight 1, known outliers weight 0. Defaults follow GTSAM's
``GncParams`` (mu_step 1.4, cost_rtol 1e-5, weights_tol 1e-4, 100 iterations); unlike
GTSAM (which first solves the unweighted problem, then restarts each inner solve from
the initial values), the first weights are computed at the initial values
(``initial_solve=True``: at the unweighted solution) and each inner solve starts from the
previous estimate (``warm_start=False``: from the initial values).

GNC judges a factor by its residual, which a wrong factor can keep small by bending the
estimate toward itself (a loop closure with high leverage), and a right factor can look
large at an estimate bent by what was wrongly kept or rejected. With TLS a *local search*
on the TLS objective ``½ Σ min(s, c̄²)`` follows (not in GTSAM): each kept factor gets
its deletion statistic T_k (what removing it and re-solving takes off ``Σ s``, its
studentised deleted residual; :func:`~jaxpose.graph.deletion_statistics`), each
rejected one its addition statistic (what adding it and re-solving adds to ``Σ s``: the
innovation test; :mod:`~jaxpose.graph._snooping`). In the linearised model deleting a
kept factor lowers the objective by ``½(T_k − c̄²)``, re-admitting a rejected one by
``½(c̄² − T_k)``; the move with the largest gain is made and the graph re-solved, and
the move is kept only if the exact TLS objective did decrease; this repeats until no
move gains, one is not kept, or the budgets run out (``max_deletions``, default 10;
``max_readmissions``, default 50). A rejected factor qualifies for re-admission only
when its statistic is below the median of an inlier's (``readmit_probability``): a
wrong one just below c̄² also lowers the objective, a little, and bends the estimate
(intel with 30 % wrong loop closures, seed 1). Each move costs one selected inversion
and one inner solve (manhattan with 50 % wrong loop closures: seed 2, one deletion,
aligned APE 13.0 → 2.1, then 14 re-admitted true loop closures, 1.61; seed 3, 15
re-admissions and two deletions, 1.91 → 0.20).

Weights enter the inner solve by scaling each factor's square-root information by
``√w_k`` (a zero weight removes the factor). The whole outer loop is one
``lax.while_loop`` around the inner solve, jitted once (``eqx.filter_jit``).
"""

from __future__ import annotations

import numbers
from collections.abc import Callable
from typing import Any

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from scipy import special

from .._precision import full_precision
from ..lie._base import runtime_check
from ..optim._solve import least_squares
from ..results import Results
from . import _snooping as snooping
from ._problem import FactorGraph, check_structure, check_variables, factor_residuals, residual_dim
from ._solve import solve

Array = jax.Array

SURROGATES = ("tls", "gm")
INNER_SOLVERS = ("sparse", "dense")


# ----------------------------------------------------------------------------------
# Closed forms of the paper
# ----------------------------------------------------------------------------------
def tls_weights(s: Array, mu: Array, barc_sq: Array) -> Array:
    """TLS weight update (Yang et al. 2020, eq. 14) for squared residuals ``s``.

    ``w = 1`` for ``s ≤ μ/(μ+1)·c̄²``, ``0`` for ``s ≥ (μ+1)/μ·c̄²``, otherwise
    ``√(c̄² μ(μ+1)/s) − μ``; all arguments broadcast, result in [0, 1]."""
    s, mu, barc_sq = jnp.broadcast_arrays(jnp.asarray(s), jnp.asarray(mu), jnp.asarray(barc_sq))
    lower = mu / (mu + 1.0) * barc_sq
    upper = (mu + 1.0) / mu * barc_sq
    safe_s = jnp.where(s > 0, s, 1.0)
    mid = jnp.sqrt(barc_sq * mu * (mu + 1.0) / safe_s) - mu
    w = jnp.where(s <= lower, 1.0, jnp.where(s >= upper, 0.0, mid))
    return jnp.clip(w, 0.0, 1.0)


def gm_weights(s: Array, mu: Array, barc_sq: Array) -> Array:
    """Geman–McClure weight update (Yang et al. 2020, eq. 12): ``(μc̄² / (s + μc̄²))²``."""
    mc = jnp.asarray(mu) * jnp.asarray(barc_sq)
    return jnp.square(mc / (jnp.asarray(s) + mc))


def initial_mu(surrogate: str, s: Array, barc_sq: Array, mask: Array | None = None) -> Array:
    """μ₀ of Remark 5 (as GTSAM): TLS ``min_k c̄²/(2 s_k − c̄²)`` over factors with
    ``2 s_k > c̄²`` (clamped to ≥ 1e-6; −1 when no factor exceeds, i.e. nothing to
    reject); GM ``max_k 2 s_k / c̄²``. ``mask`` selects the factors considered."""
    s = jnp.asarray(s)
    mask = jnp.ones(s.shape, bool) if mask is None else jnp.asarray(mask, bool)
    barc_sq = jnp.broadcast_to(barc_sq, s.shape)
    if surrogate == "gm":
        return jnp.max(jnp.where(mask, 2.0 * s / barc_sq, 0.0), initial=0.0)
    excess = 2.0 * s - barc_sq
    ok = mask & (excess > 0)
    cand = jnp.where(ok, barc_sq / jnp.where(ok, excess, 1.0), jnp.inf)
    mu = jnp.min(cand, initial=jnp.inf)
    mu = jnp.where((mu >= 0) & (mu < 1e-6), 1e-6, mu)
    return jnp.where(jnp.isfinite(mu) & (mu > 0), mu, -1.0)


def chi2_quantile(probability: float, dof: int) -> float:
    """Quantile of the χ² distribution with ``dof`` degrees of freedom (MATLAB's
    ``chi2inv``, scipy's ``chi2.ppf``): 2·P⁻¹(dof/2, p) by scipy's inverse regularised
    incomplete gamma functions, the upper one (of 1 − p, exact for p > ½) in the upper
    tail, so p = 1 − 1e-15 and p = 1e-300 are both resolved to rounding."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"chi2_quantile(probability={probability!r}): expected 0 < p < 1")
    if int(dof) != dof or dof < 1:
        raise ValueError(f"chi2_quantile(dof={dof!r}): expected a positive integer")
    a = 0.5 * float(dof)
    if probability > 0.5:
        return 2.0 * float(special.gammainccinv(a, 1.0 - probability))
    return 2.0 * float(special.gammaincinv(a, probability))


# ----------------------------------------------------------------------------------
# Result
# ----------------------------------------------------------------------------------
class GNCSolution(eqx.Module):
    """Result of :func:`gnc`.

    * ``variables``: the estimate after the last inner solve;
    * ``weights``: per factor group, (m,) inlier weights in [0, 1] (1 inlier, 0 outlier;
      binary at convergence with TLS); ``inliers``: ``weights > 0.5``;
    * ``barc_sq``: per factor group, (m,) inlier thresholds c̄² on ``s = rᵀΩr``;
    * ``cost``: weighted cost ``0.5·Σ w s`` at ``variables``; ``robust_cost``: the
      objective GNC minimises (:func:`objective`): ``0.5·Σ s`` over known inliers plus
      the surrogate's limit ``0.5·Σ ρ(s)`` over the other factors (TLS ``min(s, c̄²)``,
      GM ``c̄² s/(c̄² + s)``), known outliers counting nothing;
      ``initial_cost``: ``0.5·Σ s`` at the initial variables;
    * ``mu``: the last control parameter (−1: nothing to reject, one plain weighted solve);
      ``iterations``: outer GNC iterations;
      ``inner_iterations``: inner solver iterations summed over all solves;
      ``deletions`` / ``readmissions``: factors rejected / re-admitted after the loop by
      the local search (TLS, ``max_deletions`` / ``max_readmissions``);
    * ``status``: 0 converged (binary weights, μ at its limit, cost plateau, or nothing
      to reject), 1 max_steps (``max_iterations`` ran out), 3 non_finite (best estimate
      of the previous iteration kept); ``inner_status``: status of the last inner solve.
    """

    variables: Any
    weights: tuple[Array, ...]
    barc_sq: tuple[Array, ...]
    cost: Array
    robust_cost: Array
    initial_cost: Array
    mu: Array
    iterations: Array
    inner_iterations: Array
    status: Array
    inner_status: Array
    deletions: Array
    readmissions: Array

    @property
    def status_name(self) -> str:
        """``status`` as text: converged, max_steps or non_finite
        (:meth:`jaxpose.Results.name_of`)."""
        return Results.name_of(self.status)

    @property
    def inliers(self) -> tuple[Array, ...]:
        """Per factor group, (m,) booleans ``weights > 0.5``."""
        return tuple(w > 0.5 for w in self.weights)


# ----------------------------------------------------------------------------------
# Weighted graphs
# ----------------------------------------------------------------------------------
def _residual_dims(graph: FactorGraph) -> list[int]:
    """Residual dimension of each factor group (remembered per residual function)."""
    return [residual_dim(f, graph.variables) for f in graph.factors]


def weighted_graph(graph: FactorGraph, weights: Any) -> FactorGraph:
    """``graph`` with factor k of group g scaled by ``weights[g][k]`` ≥ 0 (its square-root
    information multiplied by √w; a zero weight removes the factor). ``weights``: one
    (m_g,) array per factor group. Traceable (weights may be traced)."""
    weights = tuple(weights)
    if len(weights) != len(graph.factors):
        raise ValueError(
            f"weighted_graph(weights): expected {len(graph.factors)} arrays (one per factor "
            f"group), got {len(weights)}"
        )
    dims = _residual_dims(graph)
    factors = []
    for g, (f, w, r) in enumerate(zip(graph.factors, weights, dims, strict=True)):
        w = jnp.asarray(w)
        if w.shape != (f.count,):
            raise ValueError(
                f"weighted_graph(weights[{g}]): expected shape ({f.count},) for factor "
                f"{f.name!r}, got {w.shape}"
            )
        if not isinstance(w, jax.core.Tracer) and bool(jnp.any(w < 0)):
            raise ValueError(f"weighted_graph(weights[{g}]): expected weights >= 0, got "
                             f"{float(jnp.min(w))} (factor {int(jnp.argmin(w))})")
        dtype = jnp.result_type(w.dtype, float)
        root = _sqrt_weight(w.astype(dtype))[:, None, None]
        base = jnp.eye(r, dtype=dtype) if f.sqrt_info is None else f.sqrt_info.astype(dtype)
        factors.append(
            eqx.tree_at(lambda x: x.sqrt_info, f, root * base, is_leaf=lambda x: x is None)
        )
    return eqx.tree_at(lambda x: x.factors, graph, tuple(factors))


@jax.custom_jvp
def _sqrt_weight(w: Array) -> Array:
    """√w of factor weights w ≥ 0 (negative traced weights count as 0)."""
    return jnp.sqrt(jnp.maximum(w, 0.0))


@_sqrt_weight.defjvp
def _sqrt_weight_jvp(primals: tuple[Array], tangents: tuple[Array]) -> tuple[Array, Array]:
    """d√w = ẇ / (2√w) for w > 0. At w = 0 the solution's derivative with respect to w is
    finite (the factor's cost is linear in w) but √w's is not, and the chain rule gives
    NaN: differentiating there raises instead."""
    (w,), (dw,) = primals, tangents
    out = runtime_check(
        _sqrt_weight(w), jnp.any(w <= 0),
        "weighted_graph: a weight that is differentiated is 0 (or negative): it enters as "
        "√w, whose derivative is infinite there, so the derivative would be NaN; keep "
        "differentiated weights > 0 (e.g. a sigmoid in float64, or w + 1e-12)")
    safe = jnp.where(w > 0, w, 1.0)
    return out, jnp.where(w > 0, 0.5 * dw / jnp.sqrt(safe), 0.0)


def _squared_norms(graph: FactorGraph, variables: Any) -> Array:
    """Concatenated ``s_k = |S r_k|²`` of every factor (group order), (M,)."""
    return jnp.concatenate(
        [jnp.sum(jnp.square(factor_residuals(f, variables)), -1) for f in graph.factors]
    )


def _split(flat: Array, counts: list[int]) -> tuple[Array, ...]:
    return tuple(jnp.split(flat, np.cumsum(counts)[:-1].tolist()))


def _by_group(
    name: str, graph: FactorGraph, parts: list, expected: str, unit: str,
    per_group: Callable[[int, Any, int], np.ndarray],
) -> np.ndarray:
    """``per_group(g, part, m)`` (m,) for each factor group ``g`` of ``m`` factors,
    concatenated (M,); ``parts`` must hold one entry per group (``expected`` and ``unit``
    word the error)."""
    counts = [f.count for f in graph.factors]
    if len(parts) != len(counts):
        raise ValueError(
            f"gnc({name}): expected {expected} per factor group ({len(counts)}), "
            f"got {len(parts)}{unit}"
        )
    return np.concatenate(
        [per_group(g, p, m) for g, (p, m) in enumerate(zip(parts, counts, strict=True))]
    )


def _per_factor(value: Any, name: str, graph: FactorGraph, default: Any, dtype: Any) -> np.ndarray:
    """A scalar, a (M,) array for a one-group graph, or one scalar/array per group -> (M,)."""
    n_groups = len(graph.factors)
    if value is None:
        value = default
    if np.ndim(value) == 0 or (
        n_groups == 1 and np.ndim(value) == 1 and not isinstance(value, (list, tuple))
    ):
        parts = [value] if n_groups == 1 else [value] * n_groups
    else:
        parts = list(value)

    def group(g: int, p: Any, m: int) -> np.ndarray:
        arr = np.asarray(p, dtype)
        if arr.ndim == 0:
            arr = np.full(m, arr, dtype)
        if arr.shape != (m,):
            raise ValueError(
                f"gnc({name}): factor group {g} ({graph.factors[g].name!r}) has {m} factors, "
                f"got shape {arr.shape}"
            )
        return arr

    return _by_group(name, graph, parts, "a scalar or one entry", "", group)


def _known(value: Any, name: str, graph: FactorGraph) -> np.ndarray:
    """None, indices or a boolean mask (one-group graph), or one such per group -> (M,) bool."""
    if value is None:
        return np.zeros(sum(f.count for f in graph.factors), bool)
    one = len(graph.factors) == 1 and not (
        isinstance(value, (list, tuple))
        and len(value) == 1
        and (value[0] is None or np.ndim(value[0]) == 1)
    )
    parts = [value] if one else list(value)

    def group(g: int, p: Any, m: int) -> np.ndarray:
        mask = np.zeros(m, bool)
        if p is not None:
            arr = np.asarray(p)
            if arr.dtype == bool:
                if arr.shape != (m,):
                    raise ValueError(
                        f"gnc({name}): a boolean mask for factor group {g} needs shape ({m},), "
                        f"got {arr.shape}"
                    )
                mask = arr.copy()
            else:
                arr = arr.reshape(-1)
                if arr.size and (
                    not np.issubdtype(arr.dtype, np.integer) or arr.min() < 0 or arr.max() >= m
                ):
                    raise ValueError(
                        f"gnc({name}): factor group {g} needs integer indices in [0, {m}), "
                        f"got {p!r}"[:300]
                    )
                mask[arr] = True
        return mask

    return _by_group(name, graph, parts, "indices or a mask", " entries", group)


# ----------------------------------------------------------------------------------
# Inner solvers
# ----------------------------------------------------------------------------------
def _free_indices(graph: FactorGraph) -> dict[str, np.ndarray]:
    st = graph.structure
    out = {}
    for name, free in zip(st.names, st.free, strict=True):
        try:
            mask = np.asarray(free)
        except jax.errors.TracerArrayConversionError:
            raise ValueError(
                "gnc(inner='dense'): the graph's fixed-variable masks must be concrete (call "
                "gnc outside jax.jit, or pass the graph as a static closure); gnc jits itself"
            ) from None
        out[name] = np.flatnonzero(mask > 0.5)
    return out


def _take(value: Any, idx: Any) -> Any:
    return type(value)(value.data[idx]) if hasattr(value, "data") else value[idx]


def _put(value: Any, idx: Any, part: Any) -> Any:
    if hasattr(value, "data"):
        return type(value)(value.data.at[idx].set(part.data))
    return value.at[idx].set(part)


def _inner_sparse(graph: FactorGraph, options: dict[str, Any]):
    def run(x: Any, w: tuple[Array, ...]) -> tuple[Any, Array, Array]:
        sol = solve(weighted_graph(graph, w), x, **options)
        return sol.variables, sol.status, sol.iterations

    return run


def _inner_dense(graph: FactorGraph, free: dict[str, Any], options: dict[str, Any]):
    names = [n for n in graph.structure.names if free[n].size]

    def residuals(params: Any, args: Any) -> tuple[Array, ...]:
        w, x = args
        full = dict(x)
        for n in names:
            full[n] = _put(x[n], free[n], params[n])
        return tuple(
            jnp.sqrt(wk)[:, None] * factor_residuals(f, full)
            for f, wk in zip(graph.factors, w, strict=True)
        )

    def run(x: Any, w: tuple[Array, ...]) -> tuple[Any, Array, Array]:
        params = {n: _take(x[n], free[n]) for n in names}
        w = tuple(jnp.maximum(wk, 0.0) for wk in w)
        sol = least_squares(residuals, params, (w, x), **options)
        out = dict(x)
        for n in names:
            out[n] = _put(x[n], free[n], sol.params[n])
        return out, sol.status, sol.num_steps

    return run


# ----------------------------------------------------------------------------------
# The outer loop
# ----------------------------------------------------------------------------------
def tls_objective(s: Array, barc_sq: Array, known_in: Array, known_out: Array) -> Array:
    """The objective TLS-GNC minimises, from squared whitened residuals ``s`` (M,):
    ``½ Σ s`` over known inliers + ``½ Σ min(s, c̄²)`` over the unknown factors (known
    outliers count nothing)."""
    return objective("tls", s, barc_sq, known_in, known_out)


def objective(surrogate: str, s: Array, barc_sq: Array, known_in: Array,
              known_out: Array) -> Array:
    """The objective GNC with ``surrogate`` minimises (``GNCSolution.robust_cost``), from
    squared whitened residuals ``s`` (M,): ``½ Σ s`` over known inliers + ``½ Σ ρ(s)``
    over the unknown factors, ρ(s) = ``min(s, c̄²)`` (TLS) or ``c̄² s / (c̄² + s)`` (GM);
    known outliers count nothing."""
    rho = (jnp.minimum(s, barc_sq) if surrogate == "tls"
           else barc_sq * s / (barc_sq + s))
    return 0.5 * jnp.sum(jnp.where(known_in, s, jnp.where(known_out, 0.0, rho)))


def _select(pred: Array, new: Any, old: Any) -> Any:
    """``new`` where ``pred`` else ``old``, leaf by leaf (one scalar predicate)."""
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), new, old)


@eqx.filter_jit
@full_precision
def _run(
    graph: FactorGraph,
    x0: Any,
    barc_sq: Array,
    readmit_sq: Array,
    known_in: Array,
    known_out: Array,
    free: Any,
    config: dict[str, Any],
    options: dict[str, Any],
) -> GNCSolution:
    surrogate = config["surrogate"]
    counts = [f.count for f in graph.factors]
    inner = (
        _inner_sparse(graph, options)
        if config["inner"] == "sparse"
        else _inner_dense(graph, free, options)
    )
    s0 = _squared_norms(graph, x0)
    dtype = s0.dtype
    barc_sq = jnp.asarray(barc_sq, dtype)
    readmit_sq = jnp.asarray(readmit_sq, dtype)
    unknown = ~(known_in | known_out)
    w_init = jnp.where(known_out, 0.0, 1.0).astype(dtype)

    def fix_known(w: Array) -> Array:
        return jnp.where(known_in, 1.0, jnp.where(known_out, 0.0, w)).astype(dtype)

    if config["initial_solve"]:
        x1, ist, iits = inner(x0, _split(w_init, counts))
    else:
        x1, ist, iits = x0, jnp.asarray(Results.CONVERGED), jnp.asarray(0)
    s1 = _squared_norms(graph, x1)
    cost1 = 0.5 * jnp.sum(w_init * s1)
    mu0 = initial_mu(surrogate, s0, barc_sq, unknown).astype(dtype)
    # nothing to decide (no unknown factor, or none above the threshold): the plain
    # weighted solve is the answer (already done with initial_solve; else one iteration
    # with the initial weights, marked by μ = −1)
    nothing = (mu0 <= 0) | ~jnp.any(unknown)
    mu0 = jnp.where(nothing, -1.0, mu0).astype(dtype)
    solved = nothing & config["initial_solve"]
    status0 = jnp.where(
        ~jnp.isfinite(cost1),
        Results.NON_FINITE,
        jnp.where(solved, Results.CONVERGED, Results.RUNNING),
    ).astype(jnp.int32)
    search_on = surrogate == "tls" and config["max_deletions"] + config["max_readmissions"] > 0

    init = dict(
        x=x1,
        w=w_init,
        mu=mu0,
        k=jnp.asarray(0, jnp.int32),
        cost=cost1,
        status=status0,
        inner_status=jnp.asarray(ist, jnp.int32),
        inner_its=jnp.asarray(iits, jnp.int32),
        deletions=jnp.asarray(0, jnp.int32),
        readmissions=jnp.asarray(0, jnp.int32),
    )
    if config["max_iterations"] <= 0:
        init["status"] = jnp.where(init["status"] < 0, Results.MAX_STEPS, init["status"])
    if search_on:  # phase 0: GNC, 1: local search; `final`: GNC's status
        init.update(final=init["status"], tls=tls_objective(s1, barc_sq, known_in, known_out),
                    phase=jnp.asarray(0, jnp.int32))
        init = _enter_search(init, init["status"] >= 0)
    weight_fn = tls_weights if surrogate == "tls" else gm_weights

    def gnc_weights(x: Any, mu: Array) -> Array:
        return jnp.where(
            mu <= 0, w_init, fix_known(weight_fn(_squared_norms(graph, x), jnp.abs(mu), barc_sq))
        )

    def move_candidate(x: Any, w: Array, state: dict[str, Any]) -> tuple[Array, ...]:
        """Binary ``w`` with the move of the largest linearised gain made (a kept factor
        rejected: ``T_k − c̄²``, a rejected one re-admitted: ``c̄² − T_k``, within the
        budgets), whether that gain is positive, and whether the move re-admits
        (module docstring)."""
        kept = w > 0.5
        t = jnp.concatenate(
            snooping.statistics(graph, x, config["snooping"], _split(kept, counts)))
        budget = jnp.where(kept, state["deletions"] < config["max_deletions"],
                           (state["readmissions"] < config["max_readmissions"])
                           & (t < readmit_sq))
        gain = jnp.where(kept, t - barc_sq, barc_sq - t)
        gain = jnp.where(unknown & budget & jnp.isfinite(t), gain, -jnp.inf)
        k = jnp.argmax(gain)
        binary = kept.astype(dtype)
        return binary.at[k].set(1.0 - binary[k]), gain[k] > 0, ~kept[k]

    def body(state: dict[str, Any]) -> dict[str, Any]:
        mu, x = state["mu"], state["x"]
        plain = mu <= 0
        start = x if config["warm_start"] else x0
        if search_on:
            searching = state["phase"] == 1
            no_move = (lambda x, w, _: (w, jnp.asarray(False), jnp.asarray(False)))
            w_move, worth, readmit = jax.lax.cond(searching, move_candidate, no_move, x,
                                                  state["w"], state)
            w = jnp.where(searching, w_move, gnc_weights(x, mu))
            start = _select(searching, x, start)
            x_new, ist, iits = jax.lax.cond(
                ~searching | worth,
                lambda: inner(start, _split(w, counts)),
                lambda: (x, state["inner_status"], jnp.asarray(0, jnp.int32)),
            )
        else:
            w = gnc_weights(x, mu)
            x_new, ist, iits = inner(start, _split(w, counts))
        s_new = _squared_norms(graph, x_new)
        cost_new = 0.5 * jnp.sum(w * s_new)
        finite = jnp.isfinite(cost_new)
        prev = state["cost"]
        cost_conv = jnp.abs(cost_new - prev) / jnp.maximum(prev, 1e-7) < config["cost_rtol"]
        if surrogate == "tls":
            weights_conv = jnp.all(jnp.abs(w - jnp.round(w)) <= config["weights_tol"])
            # a cost plateau stops TLS only with binary weights (then weights_conv holds):
            # in a large graph one factor's fractional weight moved the total by less
            # than cost_rtol, and CONVERGED came with w = 0.42 at s = 1.01·c̄²
            cost_conv = cost_conv & weights_conv
            mu_conv = jnp.asarray(False)
            mu_next = mu * config["mu_step"]
        else:
            weights_conv = jnp.asarray(False)
            mu_conv = jnp.abs(mu - 1.0) < 1e-9
            mu_next = jnp.maximum(1.0, mu / config["mu_step"])
        k = state["k"] + 1
        done = cost_conv | weights_conv | mu_conv | plain
        status = jnp.where(
            ~finite,
            Results.NON_FINITE,
            jnp.where(
                done,
                Results.CONVERGED,
                jnp.where(k >= config["max_iterations"], Results.MAX_STEPS, Results.RUNNING),
            ),
        ).astype(jnp.int32)
        out = dict(
            x=_select(finite, x_new, x),
            w=_select(finite, w, state["w"]),
            mu=jnp.where(done, mu, mu_next),
            k=k,
            cost=jnp.where(finite, cost_new, prev),
            status=status,
            inner_status=jnp.asarray(ist, jnp.int32),
            inner_its=state["inner_its"] + jnp.asarray(iits, jnp.int32),
            deletions=state["deletions"],
            readmissions=state["readmissions"],
        )
        if not search_on:
            return out
        tls_new = tls_objective(s_new, barc_sq, known_in, known_out)
        out.update(final=status, tls=jnp.where(finite, tls_new, state["tls"]),
                   phase=state["phase"])
        out = _enter_search(out, status >= 0)
        # a local-search move: kept only if the TLS objective decreased
        accept = worth & finite & (tls_new < state["tls"])
        n = state["deletions"] + (accept & ~readmit).astype(jnp.int32)
        n_in = state["readmissions"] + (accept & readmit).astype(jnp.int32)
        more = (n < config["max_deletions"]) | (n_in < config["max_readmissions"])
        step = dict(
            state,
            x=_select(accept, x_new, x),
            w=_select(accept, w, state["w"]),
            cost=jnp.where(accept, cost_new, prev),
            tls=jnp.where(accept, tls_new, state["tls"]),
            inner_status=jnp.where(accept, jnp.asarray(ist, jnp.int32), state["inner_status"]),
            inner_its=state["inner_its"] + jnp.asarray(iits, jnp.int32),
            deletions=n,
            readmissions=n_in,
            status=jnp.where(accept & more, Results.RUNNING, state["final"]).astype(jnp.int32),
        )
        return _select(searching, step, out)

    out = jax.lax.while_loop(lambda st: st["status"] < 0, body, init)
    s = _squared_norms(graph, out["x"])
    return GNCSolution(
        variables=out["x"],
        weights=_split(out["w"], counts),
        barc_sq=_split(barc_sq, counts),
        cost=out["cost"],
        robust_cost=objective(surrogate, s, barc_sq, known_in, known_out),
        initial_cost=0.5 * jnp.sum(s0),
        mu=out["mu"],
        iterations=out["k"],
        inner_iterations=out["inner_its"],
        status=out["status"],
        inner_status=out["inner_status"],
        deletions=out["deletions"],
        readmissions=out["readmissions"],
    )


def _enter_search(state: dict[str, Any], ended: Array) -> dict[str, Any]:
    """Where GNC's loop has ``ended`` (not non-finite), record its status in ``final``
    and go on with the local search (phase 1, running)."""
    go = ended & (state["status"] != Results.NON_FINITE) & (state["phase"] == 0)
    out = dict(state)
    out["final"] = jnp.where(go, state["status"], state["final"]).astype(jnp.int32)
    out["status"] = jnp.where(go, Results.RUNNING, state["status"]).astype(jnp.int32)
    out["phase"] = jnp.where(go, 1, state["phase"]).astype(jnp.int32)
    return out


def gnc(
    graph: FactorGraph,
    variables: Any = None,
    *,
    surrogate: str = "tls",
    barc_sq: Any = None,
    inlier_probability: float = 0.99,
    known_inliers: Any = None,
    known_outliers: Any = None,
    mu_step: float = 1.4,
    max_iterations: int = 100,
    cost_rtol: float = 1e-5,
    weights_tol: float = 1e-4,
    warm_start: bool = True,
    initial_solve: bool = False,
    max_deletions: int = 10,
    max_readmissions: int = 50,
    readmit_probability: float = 0.5,
    inner: str = "sparse",
    **solver_options: Any,
) -> GNCSolution:
    """Outlier-robust solve of a factor graph by graduated non-convexity (module docstring).

    Args:
        graph: a :class:`FactorGraph` whose factors carry no robust kernel (GNC supplies
            the robust loss); its ``variables`` are the default start.
        variables: optional starting values with the same structure.
        surrogate: ``"tls"`` (truncated least squares) or ``"gm"`` (Geman–McClure).
        barc_sq: inlier threshold c̄² on ``s = rᵀΩr``: a scalar, or one scalar / (m,)
            array per factor group (a (m,) array for a one-group graph). Default: the χ²
            quantile at ``inlier_probability`` for each group's residual dimension.
        known_inliers, known_outliers: factors whose weight stays 1 / 0: indices or a
            boolean mask (one-group graph), or one such (or None) per factor group.
        mu_step: factor of the μ update (> 1). max_iterations: outer iterations.
        cost_rtol: stop when the weighted cost changes by less than this, relatively
            (TLS: once the weights are also binary).
        weights_tol: (TLS) stop when every weight is within this of 0 or 1.
        warm_start: start each inner solve from the previous estimate (False: from the
            initial values, as GTSAM).
        initial_solve: first solve the unweighted problem and compute the first weights
            at its solution (the paper's Algorithm 1, and GTSAM); default False: the first
            weights come from the initial values. With a local inner solver and warm
            starts, an unweighted solve with many outliers throws away a good initial
            guess (intel with 50 % outlier loop closures: 10 % of the inliers then end up
            rejected; from the initial values all are classified right).
        max_deletions, max_readmissions: (TLS) after the loop, the local search (module
            docstring) rejects at most ``max_deletions`` more factors and re-admits at
            most ``max_readmissions`` rejected ones (0 and 0: off). It removes wrong
            factors whose residual is small because the estimate bent to fit them, and
            takes back right ones rejected at a bent estimate.
        readmit_probability: (TLS) a rejected factor is re-admitted only if its addition
            statistic is below the χ² quantile at this probability (default 0.5: at least
            as consistent as the median inlier), scaled as ``barc_sq`` is from
            ``inlier_probability``. A wrong factor whose statistic falls just below c̄²
            also lowers the objective a little when re-admitted, and costs far more
            (intel, 30 % wrong loop closures, seed 1: one re-admitted at T = 10.4, aligned
            APE 0.020 → 0.65).
        inner: ``"sparse"`` (:func:`jaxpose.graph.solve`; ``solver_options`` are its
            keywords, e.g. ``linear_solver``, ``stopping``) or ``"dense"``
            (:func:`jaxpose.optim.least_squares` over the stacked free variables;
            ``solver_options`` are its keywords). Dense suits small graphs.

    Returns:
        :class:`GNCSolution` (estimate, per-factor weights, status).

    The outer loop is a ``lax.while_loop`` around the inner solve, compiled once; it
    vmaps with ``inner="dense"``. Gradients: differentiating ``gnc`` itself raises;
    differentiate a fixed-weight re-solve
    (``solve(weighted_graph(graph, sol.weights), sol.variables)``) instead.
    """
    if not isinstance(graph, FactorGraph):
        raise TypeError(f"gnc(graph): expected a FactorGraph, got {type(graph).__name__}")
    if surrogate not in SURROGATES:
        raise ValueError(f"gnc(surrogate={surrogate!r}): expected one of {SURROGATES}")
    if inner not in INNER_SOLVERS:
        raise ValueError(f"gnc(inner={inner!r}): expected one of {INNER_SOLVERS}")
    if not mu_step > 1.0:
        raise ValueError(f"gnc(mu_step={mu_step!r}): expected a float > 1")
    for name, value in (("cost_rtol", cost_rtol), ("weights_tol", weights_tol)):
        if not (isinstance(value, numbers.Real) and not isinstance(value, bool) and value >= 0):
            raise ValueError(f"gnc({name}={value!r}): expected a tolerance >= 0 (NaN or a "
                             f"negative value switches the stopping test off)")
    if not (isinstance(max_iterations, (int, np.integer)) and max_iterations >= 0):
        raise ValueError(f"gnc(max_iterations={max_iterations!r}): expected an int >= 0")
    for name, value in (("max_deletions", max_deletions), ("max_readmissions", max_readmissions)):
        if not (isinstance(value, (int, np.integer)) and value >= 0):
            raise ValueError(f"gnc({name}={value!r}): expected an int >= 0")
    for name, value in (("inlier_probability", inlier_probability),
                        ("readmit_probability", readmit_probability)):
        if not 0.0 < value < 1.0:
            raise ValueError(f"gnc({name}={value!r}): expected 0 < p < 1")
    for f in graph.factors:
        if f.kernel is not None:
            raise ValueError(
                f"gnc(graph): factor {f.name!r} has a robust kernel; GNC supplies the robust "
                f"loss itself, build the graph without kernels"
            )
    dims = _residual_dims(graph)
    default = [chi2_quantile(inlier_probability, r) for r in dims]
    barc = _per_factor(barc_sq, "barc_sq", graph, default, np.float64)
    if not np.all(np.isfinite(barc) & (barc > 0)):
        raise ValueError("gnc(barc_sq): expected finite thresholds > 0")
    ratio = [chi2_quantile(readmit_probability, r) / chi2_quantile(inlier_probability, r)
             for r in dims]
    readmit = barc * _per_factor(None, "readmit_probability", graph, ratio, np.float64)
    known_in = _known(known_inliers, "known_inliers", graph)
    known_out = _known(known_outliers, "known_outliers", graph)
    if np.any(known_in & known_out):
        raise ValueError(
            f"gnc(known_inliers, known_outliers): factor {int(np.argmax(known_in & known_out))}"
            f" (flat index) is in both"
        )
    graph = check_structure(graph, "gnc")
    free = _free_indices(graph) if inner == "dense" else None
    x0 = graph.variables if variables is None else variables
    check_variables(graph, x0, "gnc(variables)")
    config = dict(
        surrogate=surrogate,
        inner=inner,
        mu_step=float(mu_step),
        max_iterations=int(max_iterations),
        cost_rtol=float(cost_rtol),
        weights_tol=float(weights_tol),
        warm_start=bool(warm_start),
        initial_solve=bool(initial_solve),
        max_deletions=int(max_deletions),
        max_readmissions=int(max_readmissions),
        snooping=(snooping.plan(graph, "dense" if inner == "dense" else "auto", "gnc")
                  if surrogate == "tls" and max_deletions + max_readmissions > 0 else None),
    )
    graph, x0 = eqxi.nondifferentiable((graph, x0), msg=(
        "gnc is not differentiable (its outer loop switches factors between inlier and "
        "outlier); differentiate a fixed-weight re-solve instead: "
        "solve(weighted_graph(graph, sol.weights), sol.variables)"))
    return _run(graph, x0, barc, readmit, known_in, known_out, free, config,
                dict(solver_options))
