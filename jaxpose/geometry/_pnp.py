"""Perspective-n-Point: EPnP (Lepetit, Moreno-Noguer & Fua, IJCV 2009), batched.

``epnp(points, pixels, intrinsics)`` returns the SE3 that maps world points into the
camera frame (the ``extrinsics`` of :func:`~jaxpose.geometry.point2pixel`), a
:class:`~jaxpose.Results` and the mean reprojection error in pixels.

Algorithm (per problem, vmapped over the batch):

1. Control points from the principal axes of the world points (``eigh`` of their
   3×3 covariance); barycentric coordinates α (N, 4).
2. The 2N × 12 system M x = 0 in normalised image coordinates (K⁻¹ applied first, so
   any upper-triangular K works); its four smallest right singular vectors from the
   symmetric eigen-decomposition of MᵀM (12 × 12, ``eigh``).
3. Betas for null-space dimensions 1, 2, 3 and Lepetit's linearised 4-dimensional
   approximation, each polished by 5 Gauss–Newton steps on the six inter-control-point
   distance constraints; camera points α·C_c, sign fixed so that Z > 0, and the pose by
   Kabsch (:func:`~jaxpose.geometry.svdtf`). The candidate with the smallest reprojection
   error wins.
4. Planar targets are handled by a second run with three control points (the two
   in-plane axes, a 2N × 9 system, 3 betas); both runs are always evaluated (static
   shapes) and the better reprojection error is kept.
5. Optional refinement (``refine=True``): Levenberg–Marquardt on the pixel reprojection
   error over SE3 with :func:`jaxpose.optim.least_squares` (right retraction).

Status (:class:`~jaxpose.Results`): CONVERGED; DEGENERATE when the world points are
(numerically) collinear — the pose is then not determined (rotation about the line is
free) and the returned estimate is only one of many; NON_FINITE when the inputs or the
estimate contain NaN/Inf; with ``refine=True``, the refinement's own status (MAX_STEPS,
DIVERGED) when it stops short of the optimum (the refined estimate is still returned).
Fewer than 4 points raises a ValueError (a shape known at trace time). CONVERGED means
a converged refinement, a local optimum of the reprojection error: with the minimal
N = 4 the null space is 4-dimensional, Lepetit's linearised β is only an approximation,
and on 23 of 500 random noise-free 4-point problems the refinement converged to a wrong
pose (mean reprojection error up to 37 px; none of 500 with N = 6). Check ``error``
against the pixel noise, or use more points.

Derivatives. EPnP's algebra is not differentiated (eigenvector derivatives are undefined
for repeated eigenvalues, which planar targets always produce). Instead the returned pose
carries the implicit-function derivative of the reprojection least-squares optimum at
that pose (a custom JVP: dT = T·Exp(δ̇), δ̇ = −H⁻¹ġ with the exact Hessian H), so the value
is unchanged and d pose / d(points, pixels, intrinsics) is exact at a refined (optimal)
pose and a first-order approximation for an unrefined one. Differentiating a result whose
status is not CONVERGED (a refinement out of steps, a degenerate configuration) raises.
The rule is written as a differentiable function of the optimum (which carries the same
rule), so second
derivatives (``jax.hessian``, ``jacfwd(jacrev)``, ``grad(grad)``) are exact as well.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from .._checks import check_count
from .._precision import full_precision
from .._safe import safe_div, safe_norm, safe_sqrt
from ..lie import SE3
from ..lie._base import skew
from ..optim._implicit import converged_only
from ..results import Results
from ._camera import point2pixel
from ._registration import svdtf
from ._util import (
    Array,
    batch_shape,
    exp_act2,
    flatten_batch,
    matrix_array,
    points_array,
    spd_solve,
)


class PnPResult(NamedTuple):
    """``transform``: SE3 (...) world → camera; ``status`` int32 (...); ``error`` (...):
    mean reprojection error in pixels at ``transform``."""

    transform: SE3
    status: Array
    error: Array

    @property
    def status_name(self) -> Any:
        """``status`` as text (``"converged"``, ...; an array of names when batched), by
        :meth:`jaxpose.Results.name_of`."""
        return Results.name_of(self.status)


_PAIRS4 = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


def _products(beta: Array) -> Array:
    """Products β_a β_b (a ≤ b), column-major over the upper triangle:
    (0,0), (0,1), (1,1), (0,2), (1,2), (2,2), (0,3), ..."""
    n = beta.shape[-1]
    return jnp.stack([beta[..., a] * beta[..., b] for b in range(n) for a in range(b + 1)], -1)


def _l_matrix(null: Array, pairs: tuple[tuple[int, int], ...]) -> Array:
    """L (P, n(n+1)/2) with L·products(β) = |Σ β_k (v_k[a] − v_k[b])|² per pair."""
    n = null.shape[0]
    dv = jnp.stack([null[:, a] - null[:, b] for a, b in pairs], 0)  # (P, n, 3)
    cols = []
    for b in range(n):
        for a in range(b + 1):
            dot = jnp.sum(dv[:, a] * dv[:, b], -1)
            cols.append(dot if a == b else 2.0 * dot)
    return jnp.stack(cols, -1)


def _gauss_newton_betas(l_mat: Array, rho: Array, beta: Array, mask: Array, steps: int = 5
                        ) -> Array:
    """Polish β on L·products(β) = ρ (small damped Gauss–Newton, monotone); β entries
    where ``mask`` is 0 stay fixed.

    Written on scalar components (lists of batch-shaped arrays, static indices): under a
    vmap over many problems every operation is elementwise over the batch, which XLA:CPU
    vectorises; tiny per-problem matmuls and minor-axis reductions it runs as scalar code."""
    n, n_rows = beta.shape[-1], l_mat.shape[-2]
    pairs = [(a, b) for b in range(n) for a in range(b + 1)]  # the order of _products
    lm = [[l_mat[i, c] for c in range(len(pairs))] for i in range(n_rows)]
    rh = [rho[i] for i in range(n_rows)]
    mk = [mask[k] for k in range(n)]

    def residual(b: list[Array]) -> list[Array]:
        prods = [b[x] * b[y] for x, y in pairs]
        return [sum(lm[i][c] * prods[c] for c in range(len(pairs))) - rh[i]
                for i in range(n_rows)]

    def step(_: int, b_arr: Array) -> Array:
        b = [b_arr[k] for k in range(n)]
        r = residual(b)
        # d products_c / d β_k: β_y for k = x, β_x for k = y (pair c = (x, y))
        jac = [[mk[k] * sum(lm[i][c] * ((b[y] if x == k else 0.0) + (b[x] if y == k else 0.0))
                            for c, (x, y) in enumerate(pairs) if k in (x, y))
                for k in range(n)] for i in range(n_rows)]
        h = jnp.stack([jnp.stack([sum(jac[i][k] * jac[i][m] for i in range(n_rows))
                                  for m in range(n)]) for k in range(n)])
        g = jnp.stack([sum(jac[i][k] * r[i] for i in range(n_rows)) for k in range(n)])
        damp = 1e-12 * (jnp.trace(h) + jnp.finfo(b_arr.dtype).tiny)
        nb = b_arr - spd_solve(h + damp * jnp.eye(n, dtype=b_arr.dtype), g)
        r_new = residual([nb[k] for k in range(n)])
        better = jnp.all(jnp.isfinite(nb)) & (sum(x * x for x in r_new) <= sum(x * x for x in r))
        return jnp.where(better, nb, b_arr)

    return jax.lax.fori_loop(0, steps, step, beta)


def _lstsq(a: Array, b: Array) -> Array:
    """Least squares a x ≈ b through the (damped) normal equations (small, smooth)."""
    h = a.T @ a
    damp = 1e-12 * (jnp.trace(h) + jnp.finfo(a.dtype).tiny)
    return spd_solve(h + damp * jnp.eye(h.shape[0], dtype=a.dtype), a.T @ b)


_COL = {(a, b): i for i, (a, b) in enumerate((a, b) for b in range(4) for a in range(b + 1))}


def _initial_betas(l_mat: Array, rho: Array) -> Array:
    """Candidate β (4, 4): null-space dimensions 1, 2, 3 and the 4-D linearisation."""
    c = _COL
    z = jnp.zeros((4,), l_mat.dtype)

    def vec(*vals: Array) -> Array:
        return jnp.concatenate([jnp.stack(vals), z[len(vals):]])

    def sign(x: Array) -> Array:
        return jnp.where(x < 0, -1.0, 1.0).astype(l_mat.dtype)

    # N = 1: β0² from the (0,0) column
    l00 = l_mat[:, c[0, 0]]
    n1 = vec(safe_sqrt(safe_div(jnp.sum(l00 * rho), jnp.sum(l00 * l00))))
    # N = 2: [b00, b01, b11]
    s = _lstsq(l_mat[:, jnp.array([c[0, 0], c[0, 1], c[1, 1]])], rho)
    b0 = safe_sqrt(jnp.abs(s[0]))
    n2 = vec(b0, safe_sqrt(jnp.abs(s[2])) * sign(s[1] * s[0]))
    # N = 3: [b00, b01, b11, b02, b12]
    s = _lstsq(l_mat[:, jnp.array([c[0, 0], c[0, 1], c[1, 1], c[0, 2], c[1, 2]])], rho)
    b0 = safe_sqrt(jnp.abs(s[0]))
    n3 = vec(b0, safe_sqrt(jnp.abs(s[2])) * sign(s[1] * s[0]), safe_div(s[3], b0) * sign(s[0]))
    # Lepetit's linearisation for N = 4: [b00, b01, b02, b03]
    s = _lstsq(l_mat[:, jnp.array([c[0, 0], c[0, 1], c[0, 2], c[0, 3]])], rho)
    b0 = safe_sqrt(jnp.abs(s[0]))
    n4 = jnp.concatenate([b0[None], safe_div(s[1:], b0) * sign(s[0])])
    return jnp.stack([n1, n2, n3, n4])


def _candidates(alpha: Array, ctrl_w: Array, planar: Array, xn: Array, pw: Array
                ) -> tuple[Array, Array]:
    """Poses (4, 7) and mean normalised reprojection errors (4,) for one control set.

    ``planar`` (bool scalar): the 4th control point is unused (α₃ ≡ 0): its columns of
    MᵀM get a large diagonal so the null space lives in the first three control points,
    only the three distance constraints among them count and β₃ ≡ 0."""
    dtype = alpha.dtype
    x, y = xn[:, 0:1], xn[:, 1:2]
    zero = jnp.zeros_like(alpha)
    # rows: [α_j, 0, −α_j x] and [0, α_j, −α_j y] for each control point j
    mx = jnp.stack([alpha, zero, -alpha * x], -1).reshape(-1, 12)
    my = jnp.stack([zero, alpha, -alpha * y], -1).reshape(-1, 12)
    m = jnp.concatenate([mx, my], 0)
    mtm = m.T @ m
    lift = jnp.where(planar, 1e3 * jnp.trace(mtm) + 1.0, 0.0)
    mtm = mtm + jnp.diag(jnp.concatenate([jnp.zeros((9,), dtype), jnp.ones((3,), dtype)])) * lift
    _, vecs = jnp.linalg.eigh(mtm)
    null = vecs[:, :4].T.reshape(4, 4, 3)  # smallest eigenvalues first
    pair_ok = jnp.asarray([b < 3 for _, b in _PAIRS4]) | ~planar
    rho = jnp.stack([jnp.sum(jnp.square(ctrl_w[a] - ctrl_w[b])) for a, b in _PAIRS4])
    rho = jnp.where(pair_ok, rho, 0.0)
    l_mat = jnp.where(pair_ok[:, None], _l_matrix(null, _PAIRS4), 0.0)
    beta_mask = jnp.where(planar, jnp.array([1.0, 1.0, 1.0, 0.0], dtype), 1.0)
    betas = _initial_betas(l_mat, rho) * beta_mask

    def pose(beta: Array) -> tuple[Array, Array]:
        beta = _gauss_newton_betas(l_mat, rho, beta, beta_mask)
        ctrl_c = jnp.einsum("k,kjd->jd", beta, null)
        pc = alpha @ ctrl_c
        pc = pc * jnp.where(jnp.mean(pc[:, 2]) < 0, -1.0, 1.0)
        t = svdtf(pw, pc).data
        proj = SE3(t).act(pw)
        z = proj[:, 2:3]
        zs = jnp.where(jnp.abs(z) > 0, z, 1.0)
        err = jnp.mean(safe_norm(proj[:, :2] / zs - xn))
        ok = jnp.all(jnp.isfinite(t)) & jnp.all(z > 0) & jnp.isfinite(err)
        return t, jnp.where(ok, err, jnp.inf)

    return jax.vmap(pose)(betas)


def _epnp_single(pw: Array, uv: Array, k: Array) -> tuple[Array, Array]:
    """EPnP for one problem: pose data (7,) world→camera and status."""
    dtype = pw.dtype
    eps = jnp.finfo(dtype).eps
    kinv = jnp.linalg.inv(k)
    rays = jnp.concatenate([uv, jnp.ones_like(uv[:, :1])], -1) @ kinv.T
    xn = rays[:, :2] / rays[:, 2:3]
    c0 = jnp.mean(pw, 0)
    xc = pw - c0
    cov = xc.T @ xc / pw.shape[0]
    lam, axes = jnp.linalg.eigh(cov)  # ascending
    lam_max = lam[2]
    floor = (jnp.sqrt(eps) * lam_max) + jnp.finfo(dtype).tiny
    sig = jnp.sqrt(jnp.maximum(lam, floor))
    # control points: centroid + one per principal axis (largest first)
    order = jnp.array([2, 1, 0])
    a_rest = (xc @ axes)[:, order] / sig[order]
    alpha = jnp.concatenate([1.0 - jnp.sum(a_rest, -1, keepdims=True), a_rest], -1)
    ctrl = jnp.concatenate([c0[None], c0 + sig[order][:, None] * axes.T[order]], 0)
    # general (4 control points) and planar (the two in-plane axes) configurations
    alpha_planar = alpha.at[:, 0].add(alpha[:, 3]).at[:, 3].set(0.0)
    poses, errs = jax.vmap(_candidates, in_axes=(0, None, 0, None, None))(
        jnp.stack([alpha, alpha_planar]), ctrl, jnp.array([False, True]), xn, pw)
    poses, errs = poses.reshape(-1, 7), errs.reshape(-1)
    best = poses[jnp.argmin(errs)]
    collinear = lam[1] <= 1e3 * eps * lam_max
    inputs_finite = jnp.all(jnp.isfinite(pw)) & jnp.all(jnp.isfinite(uv))
    finite = jnp.all(jnp.isfinite(best)) & jnp.isfinite(jnp.min(errs))
    # collinear points before a non-finite estimate: on a line every candidate can fail
    # the Z > 0 test (errors all inf), which is the degeneracy, not bad input
    status = jnp.where(~inputs_finite, Results.NON_FINITE,
                       jnp.where(collinear, Results.DEGENERATE,
                                 jnp.where(finite, Results.CONVERGED, Results.NON_FINITE)))
    best = jnp.where(jnp.all(jnp.isfinite(best)), best, SE3.identity(dtype=dtype).data)
    return best, status.astype(jnp.int32)


def _residual(t: SE3, args: tuple[Array, Array, Array]) -> Array:
    """Pixel reprojection residual (N, 2)."""
    pw, uv, k = args
    return point2pixel(pw, k, t) - uv


def _jacobian(t: SE3, args: tuple[Array, Array, Array]) -> Array:
    """d residual(T·Exp(δ)) / dδ at δ = 0, rows ordered like residual.reshape(-1): (2N, 6).

    T·Exp(δ)·p ≈ T p + R (ρ + φ × p), so d p_c / d[ρ, φ] = [R, −R [p]×]; then the
    projection u = h[:2] / h[2] with h = K p_c."""
    pw, _, k = args
    r = t.rotation().matrix()
    pc = t.act(pw)  # (N, 3)
    h = pc @ k.T
    inv_z = 1.0 / h[:, 2]
    dproj = jnp.stack([
        jnp.stack([inv_z, jnp.zeros_like(inv_z), -h[:, 0] * inv_z ** 2], -1),
        jnp.stack([jnp.zeros_like(inv_z), inv_z, -h[:, 1] * inv_z ** 2], -1),
    ], -2)  # (N, 2, 3)
    dpc = jnp.concatenate([jnp.broadcast_to(r, (pw.shape[0], 3, 3)), -r @ skew(pw)], -1)
    return jnp.einsum("nij,jk,nkl->nil", dproj, k, dpc).reshape(-1, 6)


def _refine(t: Array, pw: Array, uv: Array, k: Array, steps: int) -> tuple[Array, Array]:
    """Levenberg–Marquardt on the pixel reprojection error (jaxpose.optim), then
    :func:`_polish` where it converged: the pose and the solve's status."""
    from ..optim import LevenbergMarquardt, least_squares

    sol = least_squares(_residual, SE3(t), (pw, uv, k), solver=LevenbergMarquardt(),
                        max_steps=steps, jacobian=_jacobian)
    t = jnp.where(sol.status == Results.CONVERGED, _polish(sol.params.data, pw, uv, k),
                  sol.params.data)
    return t, sol.status


def _polish(t: Array, pw: Array, uv: Array, k: Array, steps: int = 3) -> Array:
    """Up to ``steps`` Gauss–Newton steps from a converged LM estimate, each kept only if
    it is finite and shrinks ‖Jᵀr‖∞.

    LM judges a step by the cost, which stops resolving decreases near the optimum: the
    pixel residuals carry rounding of about eps·|pixel coordinates|, so LM may stop with
    ‖Jᵀr‖∞ ~ 1e-4 (float64) where the gradient still points to an optimum ~1e-9 away. The
    gradient stays informative there; these steps bring it to its own rounding level, so
    the returned pose (and the finite differences of anything computed from it) is
    smooth in the data to that level, as the implicit derivative assumes."""
    args = (pw, uv, k)

    def gradient(t: Array) -> tuple[Array, Array, Array]:
        jac = _jacobian(SE3(t), args)
        g = jac.T @ _residual(SE3(t), args).reshape(-1)
        return jac, g, jnp.max(jnp.abs(g))

    def step(_: int, carry: tuple[Array, Array, Array, Array]) -> tuple[Array, ...]:
        t, jac, g, g_inf = carry
        t_new = SE3(t).retract(-jnp.linalg.solve(jac.T @ jac, g)).data
        jac_new, g_new, g_inf_new = gradient(t_new)
        keep = jnp.all(jnp.isfinite(t_new)) & (g_inf_new < g_inf)
        return (jnp.where(keep, t_new, t), jnp.where(keep, jac_new, jac),
                jnp.where(keep, g_new, g), jnp.where(keep, g_inf_new, g_inf))

    return jax.lax.fori_loop(0, steps, step, (t, *gradient(t)))[0]


@jax.custom_jvp
def _implicit_tangent(t: Array, pw: Array, uv: Array, k: Array, status: Array) -> Array:
    """``t`` itself; its derivative w.r.t. the data (pw, uv, k) is the implicit-function
    one of the reprojection least-squares optimum: dT = T·Exp(δ̇) with δ̇ = −H⁻¹ ġ, where
    g = Jᵀr is the gradient of the cost in the chart δ ↦ T·Exp(δ) and H its exact Hessian
    at δ = 0 (exact when T is an optimum). No derivative flows to ``t`` (an EPnP/LM
    estimate); the forward pass costs nothing. The rule is itself differentiable in
    (T*, θ), so derivatives of any order are exact at an optimum; differentiating where
    ``status`` is not CONVERGED (a refinement that ran out of steps, a degenerate
    configuration) raises."""
    return t


@_implicit_tangent.defjvp
def _implicit_tangent_jvp(primals: tuple[Array, ...], tangents: tuple[Any, ...]
                          ) -> tuple[Array, Array]:
    t, pw, uv, k, status = primals
    _, dpw, duv, dk, _ = tangents
    # the optimum itself, carrying this rule's derivative when the rule is differentiated
    # again: the tangent below is then a differentiable function of (T*(θ), θ), so second
    # and higher derivatives are exact too
    ts = SE3(_implicit_tangent(t, pw, uv, k, status))

    converged = functools.partial(
        converged_only, status=status, where="epnp",
        remedy="Refine to convergence (a larger refine_steps) and check the result's status.")

    def cost(delta: Array) -> Array:  # T·Exp(δ)·p to second order (exact Hessian at 0)
        h = ts.act(exp_act2(delta, pw)) @ k.T
        return 0.5 * jnp.sum(jnp.square(h[:, :2] / h[:, 2:] - uv))

    def grad(pw: Array, uv: Array, k: Array) -> Array:
        r = _residual(ts, (pw, uv, k)).reshape(-1)
        return _jacobian(ts, (pw, uv, k)).T @ r

    zero = jnp.zeros((6,), t.dtype)
    h = jax.hessian(cost)(zero)
    dg = converged(jax.jvp(grad, (pw, uv, k), (dpw, duv, dk))[1])
    damp = jnp.finfo(t.dtype).eps * (jnp.trace(jnp.abs(h)) + 1.0)
    ddelta = converged(-jnp.linalg.solve(h + damp * jnp.eye(6, dtype=t.dtype), dg))
    dt = jax.jvp(lambda d: ts.retract(d).data, (zero,), (ddelta,))[1]
    return ts.data, dt


def _stand_in(n: int, dtype: Any) -> tuple[Array, Array]:
    """A solved, well-conditioned PnP problem of n ≥ 4 points for the identity pose and
    K = I: points (n, 3) on a helix 2–3 m in front of the camera, their exact pixels."""
    a = jnp.arange(n, dtype=dtype)
    pts = jnp.stack([jnp.cos(a), jnp.sin(a), 2.0 + a / n], -1)
    return pts, pts[:, :2] / pts[:, 2:]


@functools.partial(jax.jit, static_argnames=("refine", "refine_steps"))
def _epnp_batched(pw: Array, uv: Array, k: Array, *, refine: bool, refine_steps: int):
    """The compiled part of :func:`epnp`: (B, N, 3), (B, N, 2), (B, 3, 3) → t (B, 7),
    status (B,), error (B,)."""
    def single(pw: Array, uv: Array, k: Array) -> tuple[Array, Array, Array]:
        pws, uvs, ks = (jax.lax.stop_gradient(x) for x in (pw, uv, k))
        t, status = _epnp_single(pws, uvs, ks)
        if refine:
            # only a finite, well-posed EPnP estimate is refined: NaN/inf data would make
            # the refinement's start cost non-finite, which least_squares raises on (an
            # error about its residual_fn instead of this function's NON_FINITE status);
            # other problems get a trivially solved stand-in (one point on the axis)
            good = (jnp.all(jnp.isfinite(pws)) & jnp.all(jnp.isfinite(uvs))
                    & jnp.all(jnp.isfinite(ks)) & jnp.all(jnp.isfinite(t))
                    & (status == Results.CONVERGED))
            ident = jnp.zeros(7, t.dtype).at[6].set(1.0)
            on_axis = jnp.zeros_like(pws).at[:, 2].set(1.0)
            t_ref, lm = _refine(jnp.where(good, t, ident), jnp.where(good, pws, on_axis),
                                jnp.where(good, uvs, 0.0),
                                jnp.where(good, ks, jnp.eye(3, dtype=ks.dtype)), refine_steps)
            ok = good & jnp.all(jnp.isfinite(t_ref))
            t = jnp.where(ok, t_ref, t)
            # a refinement that stopped short of the optimum is the routine's status
            status = jnp.where(good & (lm != Results.CONVERGED), lm, status).astype(jnp.int32)
        ok = status != Results.NON_FINITE
        # a NON_FINITE problem keeps its (non-finite) pose and gets no derivative; the
        # rule still runs for it under vmap (jnp.where evaluates both sides), so it sees a
        # solved stand-in instead of NaN data: its check would otherwise raise for the
        # whole batch, and a caller masking the problem out could not differentiate the
        # others
        stand_pw, stand_uv = _stand_in(pw.shape[0], pw.dtype)
        rule = _implicit_tangent(
            jnp.where(ok, t, jnp.zeros_like(t).at[6].set(1.0)), jnp.where(ok, pw, stand_pw),
            jnp.where(ok, uv, stand_uv), jnp.where(ok, k, jnp.eye(3, dtype=k.dtype)),
            jnp.where(ok, status, Results.CONVERGED).astype(jnp.int32))
        t = jnp.where(ok, rule, t)
        err = jnp.mean(safe_norm(_residual(SE3(t), (pw, uv, k))), -1)
        return t, status, err

    return jax.vmap(single)(pw, uv, k)


@full_precision
def epnp(
    points: Any,
    pixels: Any,
    intrinsics: Any,
    *,
    refine: bool = True,
    refine_steps: int = 10,
) -> PnPResult:
    """Camera pose from N ≥ 4 world ``points`` (..., N, 3) and their ``pixels``
    (..., N, 2) with ``intrinsics`` K (..., 3, 3); batch axes broadcast.

    Returns :class:`PnPResult` with ``transform`` (SE3 world → camera, so that
    ``point2pixel(points, K, transform) ≈ pixels``), ``status`` and ``error``.
    ``refine``: up to ``refine_steps`` Levenberg–Marquardt steps on the pixel reprojection
    error, then (when they converge) at most 3 Gauss–Newton steps kept while ‖Jᵀr‖∞
    shrinks, so the pose is the least-squares optimum to the gradient's rounding level.
    Checks run eagerly; the solve is compiled (``jax.jit``, ``refine`` and
    ``refine_steps`` static), so new data of the same shapes reuse the program."""
    fn = "epnp"
    pw = points_array(points, f"{fn}(points)", 3)
    uv = points_array(pixels, f"{fn}(pixels)", 2)
    k = matrix_array(intrinsics, f"{fn}(intrinsics)", 3)
    if pw.shape[-2] != uv.shape[-2]:
        raise ValueError(f"{fn}(points, pixels): expected the same number of points, got "
                         f"{pw.shape[-2]} and {uv.shape[-2]}")
    if pw.shape[-2] < 4:
        raise ValueError(f"{fn}(points): EPnP needs at least 4 points, got {pw.shape[-2]}")
    refine_steps = check_count(refine_steps, f"{fn}(refine_steps)")
    batch = batch_shape(pw.shape[:-2], uv.shape[:-2], k.shape[:-2],
                        names=("points", "pixels", "intrinsics"))
    dtype = jnp.result_type(pw.dtype, uv.dtype, k.dtype)
    t, status, err = _epnp_batched(
        flatten_batch(pw.astype(dtype), batch, 2), flatten_batch(uv.astype(dtype), batch, 2),
        flatten_batch(k.astype(dtype), batch, 2), refine=bool(refine),
        refine_steps=refine_steps)
    return PnPResult(SE3(t.reshape(*batch, 7)), status.reshape(batch), err.reshape(batch))


__all__ = ["PnPResult", "epnp"]
