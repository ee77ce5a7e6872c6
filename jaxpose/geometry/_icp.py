"""Iterative closest point (point-to-point and point-to-plane) in one ``lax.while_loop``.

``icp(source, target)`` returns the SE3 T with ``target ≈ T · source`` (PyPose's
convention for ``pp.module.ICP``), the number of iterations, a :class:`~jaxpose.Results` and the
final inlier RMSE / fitness. Each iteration matches every transformed source point with
its nearest target point (exact k-NN, see :func:`~jaxpose.geometry.knn`; the target's
k-d tree is built once) and then

* point-to-point: solves the corresponded problem in closed form (Kabsch, from the
  original source, so no drift accumulates);
* point-to-plane: one Gauss–Newton step on Σ w (nᵢ·(T pᵢ − qᵢ))², with the update
  applied on the left, T ← Exp(δ)·T.

Correspondences farther than ``max_distance`` are ignored. The loop stops when the
update ‖Log(T_k⁻¹ T_{k+1})‖ ≤ ``tolerance`` (status CONVERGED), after ``max_iterations``
(MAX_STEPS), with fewer than 3 inlier correspondences (DEGENERATE, last good estimate
kept) or on NaN/Inf in the inputs or the estimate (NON_FINITE, last finite estimate kept;
no iteration runs when an input is non-finite).

Derivatives. ``lax.while_loop`` is not reverse-differentiable, so the returned transform
is recomputed after the loop from its converged correspondences (which are piecewise
constant): one more Kabsch solve (point-to-point), or the loop's T carrying a custom JVP
dT = Exp(δ̇)·T, δ̇ = −H⁻¹ġ (point-to-plane, exact Hessian H of the cost). Its value is the
loop's; its derivative with respect to ``source``, ``target`` (and ``target_normals``) is
the implicit-function derivative of the fixed point (exact once converged; point-to-plane
raises when differentiated at a status other than CONVERGED), and both rules
are differentiable functions of the optimum, so second derivatives (``jax.hessian``,
``jacfwd(jacrev)``, ``grad(grad)``) are exact as well. The derivative with respect to
``init`` is zero.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count
from .._precision import full_precision
from ..lie import SE3
from ..lie._base import as_float_array, check_last_dim, runtime_check
from ..optim._implicit import converged_only
from ..results import Results
from ._kdtree import build_kdtree, query_kdtree
from ._knn import DEFAULT_BUDGET, _select, knn, resolve_method, tile_size
from ._registration import _kabsch  # weights are 0/1 here: no run-time check
from ._util import (
    Array,
    batch_shape,
    check_group,
    exp_act2,
    flatten_batch,
    points_array,
    same_count,
)

_METHODS = ("point_to_point", "point_to_plane")


class ICPResult(NamedTuple):
    """``transform`` SE3 (...) with target ≈ T·source; ``iterations`` int32 (...);
    ``status`` int32 (...) (:class:`~jaxpose.Results`); ``rmse`` (...): RMS point distance (or
    point-to-plane distance) of the inlier correspondences used by the last update;
    ``fitness`` (...): their fraction of the source points."""

    transform: SE3
    iterations: Array
    status: Array
    rmse: Array
    fitness: Array

    @property
    def status_name(self) -> Any:
        """``status`` as text (``"converged"``, ...; an array of names when batched), by
        :meth:`jaxpose.Results.name_of`."""
        return Results.name_of(self.status)


def _plane_step(t: Array, src: Array, q: Array, nrm: Array, w: Array) -> Array:
    """One left-perturbation Gauss–Newton step of point-to-plane ICP (returns SE3 data)."""
    moved = SE3(t).act(src)
    r = jnp.sum(nrm * (moved - q), -1)  # (N,)
    jac = jnp.concatenate([nrm, jnp.cross(moved, nrm)], -1)  # (N, 6): d r / d[ρ, φ]
    h = jnp.einsum("n,ni,nj->ij", w, jac, jac)
    g = jnp.einsum("n,ni,n->i", w, jac, r)
    damp = jnp.finfo(t.dtype).eps * (jnp.trace(h) + 1.0)
    delta = -jnp.linalg.solve(h + damp * jnp.eye(6, dtype=t.dtype), g)
    return SE3.exp(delta).compose(SE3(t)).data


@jax.custom_jvp
def _plane_implicit(t: Array, src: Array, q: Array, nrm: Array, w: Array,
                    status: Array) -> Array:
    """``t`` itself (SE3 data); its derivative w.r.t. (src, q, nrm) is the implicit-function
    one of the point-to-plane optimum: dT = Exp(δ̇)·T with δ̇ = −H⁻¹ġ, g the gradient of
    the cost in the left chart δ ↦ Exp(δ)·T and H its exact Hessian at δ = 0. No derivative
    flows to ``t`` or ``w`` (piecewise-constant inlier mask). Differentiating where the
    loop's ``status`` is not CONVERGED (``t`` is then not the optimum) raises."""
    return t


@_plane_implicit.defjvp
def _plane_implicit_jvp(primals: tuple[Array, ...], tangents: tuple[Any, ...]
                        ) -> tuple[Array, Array]:
    t, src, q, nrm, w, status = primals
    _, dsrc, dq, dnrm, _, _ = tangents
    # the optimum itself, carrying this rule when the rule is differentiated again: the
    # tangent is then a differentiable function of (T*(θ), θ), so higher orders are exact
    ts = _plane_implicit(t, src, q, nrm, w, status)

    converged = functools.partial(
        converged_only, status=status, where="icp(method='point_to_plane')",
        remedy="Give it more iterations (max_iterations) or a looser tolerance.")

    def cost(delta: Array) -> Array:  # Exp(δ)·T·p to second order (exact Hessian at 0)
        moved = exp_act2(delta, SE3(ts).act(src))
        return 0.5 * jnp.sum(w * jnp.square(jnp.sum(nrm * (moved - q), -1)))

    def grad(src: Array, q: Array, nrm: Array) -> Array:
        moved = SE3(ts).act(src)
        r = jnp.sum(nrm * (moved - q), -1)
        jac = jnp.concatenate([nrm, jnp.cross(moved, nrm)], -1)
        return jnp.einsum("n,ni,n->i", w, jac, r)

    zero = jnp.zeros((6,), t.dtype)
    h = jax.hessian(cost)(zero)
    dg = converged(jax.jvp(grad, (src, q, nrm), (dsrc, dq, dnrm))[1])
    damp = jnp.finfo(t.dtype).eps * (jnp.trace(jnp.abs(h)) + 1.0)
    ddelta = converged(-jnp.linalg.solve(h + damp * jnp.eye(6, dtype=t.dtype), dg))
    dt = jax.jvp(lambda d: SE3.exp(d).compose(SE3(ts)).data, (zero,), (ddelta,))[1]
    return ts, dt


def _plane_rmse(t: Array, src: Array, q: Array, nrm: Array, w: Array) -> Array:
    r = jnp.sum(nrm * (SE3(t).act(src) - q), -1)
    return _weighted_rms(r[:, None], w)


def _spread(src: Array, w: Array) -> Array:
    """True when the weighted source points are not all on one line (or one point): the
    second largest eigenvalue of their scatter exceeds rounding level. Collinear points
    leave the rotation about their line undetermined (Results.DEGENERATE)."""
    c = jnp.sum(w[:, None] * src, 0) / jnp.maximum(jnp.sum(w), 1.0)
    d = (src - c) * w[:, None]
    scale = jnp.max(jnp.abs(d))
    d = d / jnp.where(jnp.isfinite(scale) & (scale > 0), scale, 1.0)  # no overflow at 1e200
    ev = jnp.linalg.eigvalsh(d.T @ d)
    return ev[1] > 1e3 * jnp.finfo(src.dtype).eps * ev[2]


def _weighted_rms(diff: Array, w: Array) -> Array:
    """``sqrt(Σ w‖d‖² / max(Σw, 1))`` for rows ``diff`` (N, k), scale-safe: the squares
    are formed after dividing by the largest weighted entry, so distances of 1e200 give
    1e200 rather than inf."""
    diff = jnp.where(w[:, None] > 0, diff, 0.0)
    s = jnp.max(jnp.abs(diff))
    s = jnp.where(jnp.isfinite(s) & (s > 0), s, 1.0)
    ms = jnp.sum(w * jnp.sum(jnp.square(diff / s), -1)) / jnp.maximum(jnp.sum(w), 1.0)
    return s * jnp.sqrt(ms)


def _icp_single(
    src: Array, tgt: Array, nrm: Array | None, init: Array, max_iterations: Array,
    tolerance: Array, max_distance: Array, *, plane: bool, use_tree: bool, tile: int,
) -> ICPResult:
    n = src.shape[0]
    dtype = src.dtype
    src_c, tgt_c = jax.lax.stop_gradient(src), jax.lax.stop_gradient(tgt)
    nrm_c = None if nrm is None else jax.lax.stop_gradient(nrm)
    # the derivative with respect to init is zero (documented); the loop is not reverse-
    # differentiable, so jax.grad with respect to init (or what computes it) raised
    init = jax.lax.stop_gradient(init)
    tree = build_kdtree(tgt_c) if use_tree else None
    gate = jnp.square(max_distance.astype(dtype))  # +inf: no gate

    def nearest(moved: Array, hint: Array) -> Array:
        if tree is not None:  # the previous correspondences seed the search bound
            return query_kdtree(tree, moved, 1, hint=hint)[1][:, 0]
        return _select(moved, tgt_c, 1, tile, False)[:, 0]

    def update(t: Array, idx: Array) -> tuple[Array, Array, Array]:
        moved = SE3(t).act(src_c)
        d2 = jnp.sum(jnp.square(moved - tgt_c[idx]), -1)
        w = (d2 <= gate).astype(dtype)
        if plane:
            return _plane_step(t, src_c, tgt_c[idx], nrm_c[idx], w), w, d2
        return _kabsch(src_c, tgt_c[idx], w), w, d2

    class State(NamedTuple):
        t: Array  # last accepted estimate
        t_prev: Array  # the estimate its correspondences were found at
        idx: Array  # those correspondences
        it: Array
        accepted: Array  # at least one accepted update
        status: Array
        done: Array

    def cond(s: State) -> Array:
        return ~s.done & (s.it < max_iterations)

    def body(s: State) -> State:
        # vmapped, the body also runs for problems that have stopped (their results are
        # discarded); one that stopped on NaN data would send NaN queries to the k-d tree,
        # whose check raises for the whole batch: they search from the origin instead
        moved = jnp.where(s.done, 0.0, SE3(s.t).act(src_c))
        idx = nearest(moved, s.idx)
        t_new, w, _ = update(s.t, idx)
        finite = jnp.all(jnp.isfinite(t_new))
        enough = (jnp.sum(w) >= 3) & _spread(src_c, w)
        ok = finite & enough
        step = jnp.linalg.norm(SE3(t_new).rminus(SE3(s.t)))
        converged = ok & (step <= tolerance)
        status = jnp.where(~enough, Results.DEGENERATE,
                           jnp.where(~finite, Results.NON_FINITE, Results.CONVERGED))
        return State(
            t=jnp.where(ok, t_new, s.t),
            t_prev=jnp.where(ok, s.t, s.t_prev),
            idx=jnp.where(ok, idx, s.idx),
            it=s.it + 1,
            accepted=s.accepted | ok,
            status=status.astype(jnp.int32),
            done=converged | ~ok,
        )

    zero_idx = jnp.zeros((n,), jnp.int32)
    finite_in = (jnp.all(jnp.isfinite(src_c)) & jnp.all(jnp.isfinite(tgt_c))
                 & jnp.all(jnp.isfinite(init)))
    if nrm_c is not None:
        finite_in = finite_in & jnp.all(jnp.isfinite(nrm_c))
    s0 = State(init, init, zero_idx, jnp.asarray(0, jnp.int32), jnp.asarray(False),
               jnp.where(finite_in, Results.CONVERGED, Results.NON_FINITE).astype(jnp.int32),
               ~finite_in)
    s = jax.lax.while_loop(cond, body, s0)
    status = jnp.where(s.done, s.status, Results.MAX_STEPS).astype(jnp.int32)
    accepted = s.accepted

    # differentiable re-solve from the converged correspondences (value = loop's)
    idx = s.idx
    moved = SE3(jax.lax.stop_gradient(s.t_prev)).act(src_c)
    w = (jnp.sum(jnp.square(moved - tgt_c[idx]), -1) <= gate).astype(dtype)
    # a problem with no accepted update returns its start (derivative zero), but the
    # re-solve below is still differentiated: it sees zeros, not data that may be NaN
    # (0·NaN in the batch's gradient), and a converged status (forward mode and higher
    # orders raise for a non-converged one even where its loss is masked out)
    def data(x: Array) -> Array:
        return jnp.where(accepted, x, 0.0)

    if plane:
        t_fin = _plane_implicit(jax.lax.stop_gradient(s.t), data(src), data(tgt[idx]),
                                data(nrm[idx]), w,
                                jnp.where(accepted, status, Results.CONVERGED))
        rmse = _plane_rmse(s.t, src_c, tgt_c[idx], nrm_c[idx], w)
    else:
        t_fin = _kabsch(data(src), data(tgt[idx]), w)
        diff = SE3(jax.lax.stop_gradient(s.t)).act(src_c) - tgt_c[idx]
        rmse = _weighted_rms(diff, w)
    t_out = jnp.where(accepted, t_fin, s.t)
    fitness = jnp.where(accepted, jnp.sum(w) / n, 0.0)
    rmse = jnp.where(accepted, rmse, jnp.nan)
    # an accepted estimate whose transform or residual is not finite is not a success
    bad = accepted & ~(jnp.isfinite(rmse) & jnp.all(jnp.isfinite(t_out)))
    status = jnp.where(bad, Results.NON_FINITE, status).astype(jnp.int32)
    return ICPResult(SE3(t_out), s.it, status, rmse, fitness)


@full_precision
def icp(
    source: Any,
    target: Any,
    init: SE3 | None = None,
    *,
    method: str = "point_to_point",
    target_normals: Any = None,
    max_iterations: int = 50,
    tolerance: float = 1e-6,
    max_distance: float | None = None,
    knn_method: str = "auto",
    budget: int = DEFAULT_BUDGET,
) -> ICPResult:
    """Register ``source`` (..., N, 3) to ``target`` (..., M, 3): target ≈ T · source.

    ``init``: initial SE3 (batch broadcastable), identity by default. ``method``:
    ``"point_to_point"`` or ``"point_to_plane"`` (needs ``target_normals`` (..., M, 3),
    e.g. from :func:`estimate_normals`). ``max_distance``: correspondence gate (None:
    all pairs). ``knn_method``: as :func:`~jaxpose.geometry.knn` ``method``.
    Batches are vmapped. Returns :class:`ICPResult`."""
    fn = "icp"
    if method not in _METHODS:
        raise ValueError(f"{fn}(method): expected one of {_METHODS}, got {method!r}")
    src = points_array(source, f"{fn}(source)", 3, min_points=1)
    tgt = points_array(target, f"{fn}(target)", 3, min_points=1)
    plane = method == "point_to_plane"
    shapes, names = [src.shape[:-2], tgt.shape[:-2]], ["source", "target"]
    nrm = None
    if plane:
        if target_normals is None:
            raise ValueError(f"{fn}(target_normals): method='point_to_plane' needs target "
                             f"normals (..., M, 3); see estimate_normals")
        nrm = points_array(target_normals, f"{fn}(target_normals)", 3, min_points=1)
        same_count(tgt, nrm, f"{fn}(target)", f"{fn}(target_normals)")
        shapes.append(nrm.shape[:-2])
        names.append("target_normals")
    elif target_normals is not None:
        raise ValueError(f"{fn}(target_normals): only used by method='point_to_plane'")
    if init is not None:
        check_group(init, SE3, f"{fn}(init)")
        shapes.append(init.shape)
        names.append("init")
    if isinstance(max_iterations, bool) or (isinstance(max_iterations, int)
                                            and max_iterations < 0):
        raise ValueError(f"{fn}(max_iterations): expected an int ≥ 0, got {max_iterations!r}")
    if (max_distance is not None and not isinstance(max_distance, jax.core.Tracer)
            and not np.all(np.asarray(max_distance) > 0)):
        raise ValueError(f"{fn}(max_distance): expected a positive number or None, got "
                         f"{max_distance!r}")
    batch = batch_shape(*shapes, names=tuple(names))
    dtype = jnp.result_type(src.dtype, tgt.dtype, *(() if nrm is None else (nrm.dtype,)))
    n, m = src.shape[-2], tgt.shape[-2]
    use_tree = resolve_method(knn_method, n, m) == "kdtree"
    tile = tile_size(n, m, budget)
    init_data = (SE3.identity(dtype=dtype).data if init is None else init.data.astype(dtype))

    srcf = flatten_batch(src.astype(dtype), batch, 2)
    tgtf = flatten_batch(tgt.astype(dtype), batch, 2)
    nrmf = None if nrm is None else flatten_batch(nrm.astype(dtype), batch, 2)
    initf = flatten_batch(init_data, batch, 1)
    gate = jnp.asarray(jnp.inf if max_distance is None else max_distance, dtype)
    if isinstance(max_distance, jax.core.Tracer):  # a known one was checked above
        gate = runtime_check(gate, ~jnp.all(gate > 0), f"{fn}(max_distance): expected a "
                             "positive number or None (checked under jit)")
    out = _icp_batched(srcf, tgtf, nrmf, initf, jnp.asarray(max_iterations, jnp.int32),
                       jnp.asarray(tolerance, dtype), gate, plane=plane, use_tree=use_tree,
                       tile=tile)
    return jax.tree.map(lambda x: x.reshape(*batch, *x.shape[1:]), out)


@functools.partial(jax.jit, static_argnames=("plane", "use_tree", "tile"))
def _icp_batched(srcf: Array, tgtf: Array, nrmf: Array | None, initf: Array,
                 max_iterations: Array, tolerance: Array, max_distance: Array, **kw: Any
                 ) -> ICPResult:
    single = lambda s, t, nn, i: _icp_single(s, t, nn, i, max_iterations, tolerance,
                                             max_distance, **kw)
    return jax.vmap(single, in_axes=(0, 0, None if nrmf is None else 0, 0))(
        srcf, tgtf, nrmf, initf)


@jax.custom_jvp
def _smallest_eigenvector(a: Array) -> Array:
    """Unit eigenvector (..., 3) of the smallest eigenvalue of symmetric PSD (..., 3, 3)."""
    return jnp.linalg.eigh(a)[1][..., :, 0]


@_smallest_eigenvector.defjvp
def _smallest_eigenvector_jvp(primals: tuple[Array], tangents: tuple[Array]
                              ) -> tuple[Array, Array]:
    """dv = −B⁺ dA v with B = A − λ₀ I (λ₀ = vᵀ A v): only v's own eigenvalue need be
    simple. (The eigh derivative has 1/(λᵢ − λⱼ) for every pair: two equal in-plane
    eigenvalues, as on a regular grid, gave inf, and NaN in reverse mode.) B⁺ acts on
    v's complement as the inverse of B/s + v vᵀ (s = tr B; eigenvalues 1 on v and
    (λᵢ − λ₀)/s): written with v and A only, so it differentiates again. Where λ₀ is not
    simple (collinear or coincident neighbours) the normal is not unique and its
    derivative is returned as 0 (it was NaN)."""
    (a,), (da,) = primals, tangents
    v = _smallest_eigenvector(a)
    lam = jnp.einsum("...i,...ij,...j->...", v, a, v)
    eye = jnp.eye(3, dtype=a.dtype)
    b = a - lam[..., None, None] * eye
    s = jnp.trace(b, axis1=-2, axis2=-1)
    w = jax.lax.stop_gradient(jnp.linalg.eigvalsh(a))
    # not simple: a gap at eigh's rounding level (1e3·eps zeroed float32 strips 1 % wide,
    # gap/s ~ 1e-4); NaN stays NaN
    ok = ~(w[..., 1] - w[..., 0] <= 64 * jnp.finfo(a.dtype).eps * s)
    s = jnp.where(ok, s, 1)[..., None, None]  # each of B and dA is divided once by s
    m = jnp.where(ok[..., None, None], b / s + v[..., :, None] * v[..., None, :], eye)
    y = ((da / s) @ v[..., None])[..., 0]
    project = lambda z: z - v * jnp.sum(v * z, -1, keepdims=True)  # noqa: E731
    x = project(jnp.linalg.solve(m, project(y)[..., None])[..., 0])
    return v, jnp.where(ok[..., None], -x, 0)


def estimate_normals(
    points: Any, k: int = 16, viewpoint: Any = None, method: str = "auto"
) -> Array:
    """Unit normals (..., N, 3) of a cloud (..., N, 3) from the k nearest neighbours
    (the eigenvector of the smallest eigenvalue of the local covariance; the point itself
    counts as a neighbour). Orientation is arbitrary unless ``viewpoint`` (…, 3) is given,
    then normals face it. ``k`` is clipped to N. Differentiable at any order where the
    smallest eigenvalue is simple (also on regular grids, whose in-plane eigenvalues are
    equal); where it is not (collinear or coincident neighbours: the normal is not
    unique) the derivative is 0."""
    p = points_array(points, "estimate_normals(points)", 3, min_points=3)
    k = check_count(k, "estimate_normals(k)", minimum=3)
    k = min(k, p.shape[-2])
    idx = knn(p, p, k, method=method).indices  # (..., N, k)
    nb = jnp.take_along_axis(p[..., None, :, :], idx[..., None], axis=-2)  # (..., N, k, 3)
    centered = nb - jnp.mean(nb, -2, keepdims=True)
    cov = jnp.einsum("...ki,...kj->...ij", centered, centered)
    nrm = _smallest_eigenvector(cov)
    if viewpoint is not None:
        v = as_float_array(viewpoint, "estimate_normals(viewpoint)").astype(p.dtype)
        check_last_dim(v, 3, "estimate_normals(viewpoint)", "[x, y, z]")
        sign = jnp.sign(jnp.sum(nrm * (v[..., None, :] - p), -1, keepdims=True))
        nrm = nrm * jnp.where(sign == 0, 1.0, sign)
    return nrm


__all__ = ["ICPResult", "estimate_normals", "icp"]
