"""Closed-form registration of corresponded point sets: Kabsch (SE3) and Umeyama (Sim3).

Both solve ``min Σᵢ wᵢ |target_i − T(source_i)|²`` over proper rigid (or similarity)
transforms T, so ``target ≈ T · source``. The rotation is the maximiser of tr(Rᵀ H) over
SO(3) (H the weighted cross-covariance): H's polar factor by Newton's iteration where
det H > 0 and it converges (elementwise code), else by SVD with the reflection fix
``R = U diag(1, 1, det(U Vᵀ)) Vᵀ`` — never a reflection, even when the point sets are
mirror images or coplanar.

Derivatives do not go through the SVD (whose derivative is undefined whenever two
singular values coincide, e.g. for symmetric clouds): the rotation has a custom JVP from
the optimality condition ``sym(Rᵀ H)``: dR = R [ω]× with
``(tr(S) I − S) ω = vee(Rᵀ dH − dHᵀ R)``, S = Rᵀ H. That system is singular only when the
rotation itself is not unique (collinear or coincident points); there a Tikhonov-regularised
solve returns the minimum-norm derivative instead of Inf/NaN.

Degenerate inputs (documented status, no exception): collinear points leave the rotation
about the line free (a minimiser is still returned, so ``T · source`` still matches
``target``); a single point gives a pure translation; zero total weight gives identity.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap

from .. import _small_linalg as small_linalg
from .._precision import full_precision
from .._safe import safe_div
from ..lie import SE3, SO3, Sim3
from ..lie._base import as_float_array, runtime_check, skew, vee
from ._util import Array, batch_shape, points_array, same_count


def _det3(m: Array) -> Array:
    """Determinant of (..., 3, 3) matrices by cofactors (elementwise code; jnp.linalg.det
    runs one LU factorisation per matrix)."""
    return (m[..., 0, 0] * (m[..., 1, 1] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 1])
            - m[..., 0, 1] * (m[..., 1, 0] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 0])
            + m[..., 0, 2] * (m[..., 1, 0] * m[..., 2, 1] - m[..., 1, 1] * m[..., 2, 0]))


@jax.custom_jvp
def optimal_rotation(h: Array) -> Array:
    """argmax over R ∈ SO(3) of tr(Rᵀ H) for H (..., 3, 3) → R (..., 3, 3): the polar
    factor of H by Newton's iteration where that converges to a rotation (det H > 0, H
    not too ill-conditioned: elementwise code, no LAPACK call), else by SVD with the
    reflection fix."""
    return _rotation(h)


@custom_vmap
def _rotation(h: Array) -> Array:
    """:func:`optimal_rotation`'s value: the SVD runs only when some matrix needs it. Under
    ``vmap`` the batch goes through as leading axes (:func:`_rotation_vmap`): the ``cond``
    would otherwise become a ``select`` running both branches (1.6x the time of batched
    ``svdtf`` at B = 100 000)."""
    r, ok = _polar_rotation(h)
    return jax.lax.cond(jnp.all(ok), lambda: r,
                        lambda: jnp.where(ok[..., None, None], r, _svd_rotation(h)))


@_rotation.def_vmap
def _rotation_vmap(axis_size: int, in_batched: list[bool], h: Array) -> tuple[Array, bool]:
    (batched,) = in_batched
    return _rotation(h), batched  # h's batch axis is its leading one


POLAR_STEPS = 8
"""Newton steps of :func:`_polar_rotation`: with its scaling and the gate
:data:`POLAR_MIN_DET`, a near-rotation needs 3–4, the worst accepted H about 7."""

POLAR_MIN_DET = 100
"""Newton's iteration is used where det(H)/‖H‖³ ≥ ``POLAR_MIN_DET``·eps (Frobenius norm;
≤ σ₂σ₃/σ₁²). Below, cof(H) — Newton's first inverse — is rounding noise in its smallest
direction, the iteration converges to the polar factor of another matrix (an O(1) wrong
rotation for nearly collinear points, σ₂ = σ₃ = 1e-10 in float64), and the SVD, whose
error is ~eps·σ₁/(σ₂ + σ₃), is used instead. Measured above the gate, float32 and
float64: Newton at least as accurate as the SVD (tests)."""


def _polar_rotation(h: Array) -> tuple[Array, Array]:
    """(R, ok): the orthogonal polar factor of H (..., 3, 3) by Newton's iteration
    X ← (γX + (γX)⁻ᵀ)/2 from X = H/‖H‖, γ = (‖X⁻¹‖/‖X‖)^½ (Frobenius norms; Higham 1986),
    X⁻¹ by the adjugate (:func:`jaxpose._small_linalg.inv`); ok where det(H)/‖H‖³ ≥
    :data:`POLAR_MIN_DET`·eps (so det H > 0: then the polar factor is the maximiser) and
    it converged (|XᵀX − I| ≤ 64·eps, det X > 0). Not ok: H singular or nearly (two small
    singular values), a reflection, NaN."""
    def frobenius_sq(m: Array) -> Array:
        return jnp.sum(m * m, axis=(-2, -1))

    def newton(_: Any, x: Array) -> Array:
        inv_t = jnp.swapaxes(small_linalg.inv(x), -1, -2)
        gamma = jnp.sqrt(jnp.sqrt(frobenius_sq(inv_t) / frobenius_sq(x)))[..., None, None]
        return 0.5 * (gamma * x + inv_t / gamma)

    eps = jnp.finfo(h.dtype).eps
    x0 = h / jnp.sqrt(frobenius_sq(h))[..., None, None]
    # a loop: XLA:CPU compiles it into one function (the steps unrolled were ~40 calls)
    x = jax.lax.fori_loop(0, POLAR_STEPS, newton, x0)
    gram = jnp.swapaxes(x, -1, -2) @ x
    err = jnp.max(jnp.abs(gram - jnp.eye(3, dtype=h.dtype)), axis=(-2, -1))
    ok = ((_det3(x0) >= POLAR_MIN_DET * eps) & (err <= 64 * eps)
          & (_det3(x) > 0))  # NaN: not ok
    return x, ok


def _svd_rotation(h: Array) -> Array:
    """:func:`optimal_rotation` by SVD: R = U diag(1, 1, det(U Vᵀ)) Vᵀ."""
    u, _, vh = jnp.linalg.svd(h)
    d = _det3(u) * _det3(vh)
    d = jnp.where(d < 0, -1.0, 1.0).astype(h.dtype)
    fix = jnp.stack([jnp.ones_like(d), jnp.ones_like(d), d], -1)
    return (u * fix[..., None, :]) @ vh


@optimal_rotation.defjvp
def _optimal_rotation_jvp(primals: tuple[Array], tangents: tuple[Array]) -> tuple[Array, Array]:
    (h,), (dh,) = primals, tangents
    r = optimal_rotation(h)
    rt = jnp.swapaxes(r, -1, -2)
    s = rt @ h
    s = 0.5 * (s + jnp.swapaxes(s, -1, -2))
    eye = jnp.eye(3, dtype=h.dtype)
    tr = jnp.trace(s, axis1=-2, axis2=-1)[..., None, None]
    a = tr * eye - s  # positive semi-definite at the maximiser
    b = vee(rt @ dh - jnp.swapaxes(dh, -1, -2) @ r)
    # Tikhonov: (a² + μ² I)⁻¹ a b = a⁻¹ b up to (μ/λ)² when a is regular; → 0 along null
    # directions of a (where the rotation is not unique) instead of Inf. Solved with a
    # scaled to unit trace (μ² = eps): a⁻¹ b = (a/s)⁻¹ (b/s). tr = 0 only where S = 0
    # (coincident points): a = 0 is divided by 1 there. Each of a and b is divided once:
    # a scale of 0 + tiny and a chain (a / s) / s gave NaN derivatives on an H200 (XLA's
    # simplifier rewrites (a / s) / s as a / (s · s), and tiny² underflows to 0)
    tr_abs = jnp.abs(tr[..., 0, 0])
    scale = jnp.where(tr_abs > 0, tr_abs, 1)[..., None, None]
    a = a / scale
    lhs = a @ a + jnp.finfo(h.dtype).eps * eye
    omega = jnp.linalg.solve(lhs, a @ (b[..., None] / scale))[..., 0]
    return r, r @ skew(omega)


def _weights(weights: Any, n: int, batch: tuple[int, ...], fn: str, dtype: Any) -> Array | None:
    if weights is None:
        return None
    w = as_float_array(weights, f"{fn}(weights)").astype(dtype)
    if w.ndim < 1 or w.shape[-1] != n:
        raise ValueError(f"{fn}(weights): expected shape (..., N) with N = {n}, got shape "
                         f"{tuple(w.shape)}")
    batch_shape(batch, w.shape[:-1], names=("points", "weights"))
    return runtime_check(w, jnp.any(w < 0), f"{fn}(weights): expected non-negative weights")


def _moments(
    source: Array, target: Array, w: Array | None
) -> tuple[Array, Array, Array, Array]:
    """Weighted centroids cs, ct (..., 3), cross-covariance H = Σ w (t−ct)(s−cs)ᵀ / Σw and
    source variance Σ w |s−cs|² / Σw."""
    if w is None:
        w = jnp.ones(source.shape[:-1], source.dtype)
    w = jnp.broadcast_to(w, jnp.broadcast_shapes(w.shape, source.shape[:-1],
                                                 target.shape[:-1]))
    total = jnp.sum(w, -1)
    wn = safe_div(w, total[..., None])
    def centroid(x: Array) -> tuple[Array, Array]:
        # a second pass over the deviations corrects the first sum's rounding: in float32
        # at 1e5 offsets it was 0.2 off, biasing the scale (Σ w|s − cs|² grows by |δ|²)
        c = jnp.einsum("...n,...nk->...k", wn, x)
        c = c + jnp.einsum("...n,...nk->...k", wn, x - c[..., None, :])
        return c, x - c[..., None, :]

    cs, s0 = centroid(source)
    ct, t0 = centroid(target)
    h = jnp.einsum("...n,...ni,...nj->...ij", wn, t0, s0)
    var = jnp.einsum("...n,...nk,...nk->...", wn, s0, s0)
    return cs, ct, h, var


def _prepare(source: Any, target: Any, weights: Any, fn: str):
    s = points_array(source, f"{fn}(source)", 3)
    t = points_array(target, f"{fn}(target)", 3)
    same_count(s, t, f"{fn}(source)", f"{fn}(target)")
    batch = batch_shape(s.shape[:-2], t.shape[:-2], names=("source", "target"))
    dtype = jnp.result_type(s.dtype, t.dtype)
    w = _weights(weights, s.shape[-2], batch, fn, dtype)
    return s.astype(dtype), t.astype(dtype), w


@full_precision
def svdtf(source: Any, target: Any, weights: Any = None) -> SE3:
    """Rigid transform T (SE3, batch (...)) minimising Σ wᵢ |targetᵢ − T·sourceᵢ|².

    ``source``, ``target``: corresponded points (..., N, 3); ``weights``: optional
    non-negative (..., N). Kabsch with the reflection fix (always a proper rotation)."""
    s, t, w = _prepare(source, target, weights, "svdtf")
    return SE3(_kabsch(s, t, w))


@jax.jit
@full_precision
def _kabsch(s: Array, t: Array, w: Array | None) -> Array:
    cs, ct, h, _ = _moments(s, t, w)
    r = optimal_rotation(h)
    trans = ct - jnp.einsum("...ij,...j->...i", r, cs)
    q = SO3.from_matrix(r, check=False).data
    return jnp.concatenate([trans, q], -1)


@full_precision
def umeyama(source: Any, target: Any, with_scale: bool = True, weights: Any = None) -> Sim3:
    """Similarity T (Sim3, batch (...)) minimising Σ wᵢ |targetᵢ − (s R sourceᵢ + t)|²
    (Umeyama 1991). ``with_scale=False`` fixes s = 1 (then equal to :func:`svdtf`).
    The scale is 0 if the source points all coincide."""
    s, t, w = _prepare(source, target, weights, "umeyama")
    return Sim3(_umeyama(s, t, w, bool(with_scale)))


@functools.partial(jax.jit, static_argnums=3)
def _umeyama(s: Array, t: Array, w: Array | None, with_scale: bool) -> Array:
    cs, ct, h, var = _moments(s, t, w)
    r = optimal_rotation(h)
    if with_scale:
        # at the optimum tr(D S) of Umeyama's eq. 42 equals tr(Rᵀ H)
        c = safe_div(jnp.trace(jnp.swapaxes(r, -1, -2) @ h, axis1=-2, axis2=-1), var)
    else:
        c = jnp.ones(h.shape[:-2], h.dtype)
    trans = ct - c[..., None] * jnp.einsum("...ij,...j->...i", r, cs)
    q = SO3.from_matrix(r, check=False).data
    return jnp.concatenate([trans, q, c[..., None]], -1)


@full_precision
def svdstf(source: Any, target: Any, with_scale: bool = True) -> Sim3:
    """PyPose's name for :func:`umeyama`."""
    return umeyama(source, target, with_scale=with_scale)


__all__ = ["optimal_rotation", "svdstf", "svdtf", "umeyama"]
