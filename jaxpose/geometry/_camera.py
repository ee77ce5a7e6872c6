"""Camera geometry: homogeneous coordinates, pinhole projection, reprojection error, BAL.

Conventions (PyPose's):

* ``intrinsics`` K (..., 3, 3) maps camera-frame points to pixels, ``[u, v, 1]ᵀ ∝ K p_c``
  (any upper-triangular K; skew allowed).
* ``extrinsics`` is an :class:`~jaxpose.lie.SE3` of batch shape (...) that maps
  *world* points into the *camera* frame, ``p_c = T · p_w`` (so it is T_cw).
* Points (..., N, 3), pixels (..., N, 2); leading batch axes broadcast between points,
  pixels, intrinsics and extrinsics.
* Radial distortion acts on normalised coordinates x = (X/Z, Y/Z):
  ``x_d = x · (1 + k1 r² + k2 r⁴ + …)`` with r² = |x|², then ``[u, v, 1]ᵀ ∝ K [x_d, 1]``.

Everything is pure and smooth away from Z = 0, so it jits, vmaps and differentiates;
norms use the safe form (zero derivative at zero error, not NaN).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from .._precision import full_precision
from .._safe import safe_norm
from ..lie import SE3, SO3
from ..lie._base import as_float_array, check_last_dim
from ._util import Array, batch_shape, check_group, matrix_array, points_array

_REDUCTIONS = ("none", "sum", "norm", "mean")


def cart2homo(coordinates: Any) -> Array:
    """Append a 1: (..., D) → (..., D+1)."""
    x = as_float_array(coordinates, "cart2homo(coordinates)")
    if x.ndim == 0:
        raise ValueError("cart2homo(coordinates): expected an array of shape (..., D), got a "
                         "scalar")
    return jnp.concatenate([x, jnp.ones_like(x[..., :1])], -1)


def homo2cart(coordinates: Any) -> Array:
    """Divide by the last coordinate: (..., D+1) → (..., D).

    A last coordinate of (nearly) zero is replaced by ±tiny with its sign kept (0 counts
    as positive), as in PyPose: no 0/0 NaN, but a finite result of about x/tiny (4.5e307
    for x = 1 in float64) that overflows to ±inf once |x| exceeds about 4 (a point on the
    camera plane projects far out)."""
    x = as_float_array(coordinates, "homo2cart(coordinates)")
    if x.ndim == 0 or x.shape[-1] < 2:
        raise ValueError(f"homo2cart(coordinates): expected an array of shape (..., D+1) with "
                         f"D ≥ 1, got shape {tuple(x.shape)}")
    w = x[..., -1:]
    tiny = jnp.finfo(x.dtype).tiny
    w_safe = jnp.where(jnp.abs(w) < tiny, jnp.where(w < 0, -tiny, tiny), w)
    return x[..., :-1] / w_safe


def _intrinsics(intrinsics: Any, fn: str) -> Array:
    return matrix_array(intrinsics, f"{fn}(intrinsics)", 3)


def _distortion(distortion: Any, fn: str) -> Array | None:
    if distortion is None:
        return None
    d = as_float_array(distortion, f"{fn}(distortion)")
    if d.ndim == 0 or d.shape[-1] < 1:
        raise ValueError(f"{fn}(distortion): expected radial coefficients of shape (..., K) "
                         f"= [k1, k2, ...], got shape {tuple(d.shape)}")
    return d


def radial_distort(normalized: Any, coeffs: Any) -> Array:
    """Radial distortion of normalised coordinates (..., N, 2) with ``coeffs`` (..., K):
    x · (1 + k1 r² + k2 r⁴ + … + kK r^{2K})."""
    x = as_float_array(normalized, "radial_distort(normalized)")
    check_last_dim(x, 2, "radial_distort(normalized)", "[x, y]")
    k = _distortion(coeffs, "radial_distort")
    r2 = jnp.sum(x * x, -1)  # (..., N)
    # Horner in r²: 1 + r²(k1 + r²(k2 + ...))
    poly = jnp.zeros_like(r2)
    for i in range(k.shape[-1] - 1, -1, -1):
        poly = (poly + k[..., i, None]) * r2
    return x * (1.0 + poly)[..., None]


def point2pixel(
    points: Any, intrinsics: Any, extrinsics: SE3 | None = None, distortion: Any = None
) -> Array:
    """Project points (..., N, 3) to pixels (..., N, 2).

    ``points`` are in the camera frame, or in the world frame when ``extrinsics``
    (SE3 world→camera, batch (...)) is given. ``distortion``: optional radial
    coefficients (..., K) applied to the normalised coordinates before K."""
    fn = "point2pixel"
    p = points_array(points, f"{fn}(points)", 3, min_points=0)
    k = _intrinsics(intrinsics, fn)
    dist = _distortion(distortion, fn)
    shapes, names = [p.shape[:-2], k.shape[:-2]], ["points", "intrinsics"]
    if extrinsics is not None:
        check_group(extrinsics, SE3, f"{fn}(extrinsics)")
        shapes.append(extrinsics.shape)
        names.append("extrinsics")
    if dist is not None:
        shapes.append(dist.shape[:-1])
        names.append("distortion")
    batch_shape(*shapes, names=tuple(names))
    return _project(p, k, None if extrinsics is None else extrinsics.data, dist)


@jax.jit
@full_precision
def _project(p: Array, k: Array, ext: Array | None, dist: Array | None) -> Array:
    if ext is not None:
        p = SE3(ext[..., None, :]).act(p)
    if dist is None:
        return homo2cart(jnp.einsum("...ij,...nj->...ni", k, p))
    xd = radial_distort(homo2cart(p), dist)
    return homo2cart(jnp.einsum("...ij,...nj->...ni", k, cart2homo(xd)))


def pixel2point(
    pixels: Any, depth: Any, intrinsics: Any, extrinsics: SE3 | None = None
) -> Array:
    """Back-project pixels (..., N, 2) at ``depth`` (..., N) (the camera-frame Z) to
    points (..., N, 3): the point of Z = ``depth`` on the ray ``K⁻¹ [u, v, 1]`` in the
    camera frame, or in the world frame when ``extrinsics`` (SE3 world→camera) is given.
    No distortion model."""
    fn = "pixel2point"
    px = points_array(pixels, f"{fn}(pixels)", 2, min_points=0)
    z = as_float_array(depth, f"{fn}(depth)")
    if z.ndim < 1 or z.shape[-1] != px.shape[-2]:
        raise ValueError(f"{fn}(depth): expected shape (..., N) with N = {px.shape[-2]} "
                         f"(the number of pixels), got shape {tuple(z.shape)}")
    k = _intrinsics(intrinsics, fn)
    shapes, names = [px.shape[:-2], z.shape[:-1], k.shape[:-2]], ["pixels", "depth",
                                                                 "intrinsics"]
    if extrinsics is not None:
        check_group(extrinsics, SE3, f"{fn}(extrinsics)")
        shapes.append(extrinsics.shape)
        names.append("extrinsics")
    batch_shape(*shapes, names=tuple(names))
    return _backproject(px, z, k, None if extrinsics is None else extrinsics.data)


@jax.jit
@full_precision
def _backproject(px: Array, z: Array, k: Array, ext: Array | None) -> Array:
    rays = jnp.einsum("...ij,...nj->...ni", jnp.linalg.inv(k), cart2homo(px))
    # K is defined up to scale: normalise the rays to Z = 1 so depth is the Z coordinate
    pc = rays / rays[..., 2:] * z[..., None]
    if ext is None:
        return pc
    return SE3(ext[..., None, :]).inv().act(pc)


def reprojerr(
    points: Any,
    pixels: Any,
    intrinsics: Any,
    extrinsics: SE3 | None = None,
    reduction: str = "none",
    distortion: Any = None,
) -> Array:
    """Reprojection error ``point2pixel(points, ...) − pixels``.

    ``reduction``: ``'none'`` (..., N, 2); ``'norm'`` per-point L2 (..., N); ``'sum'``
    per-point L1 |du| + |dv| (..., N) (what PyPose documents for ``'sum'``); ``'mean'``
    mean L2 over the N points (...)."""
    fn = "reprojerr"
    if reduction not in _REDUCTIONS:
        raise ValueError(f"{fn}(reduction): expected one of {_REDUCTIONS}, got {reduction!r}")
    p = points_array(points, f"{fn}(points)", 3, min_points=0)
    px = points_array(pixels, f"{fn}(pixels)", 2, min_points=0)
    if p.shape[-2] != px.shape[-2]:
        raise ValueError(f"{fn}(points, pixels): expected the same number of points, got "
                         f"{p.shape[-2]} and {px.shape[-2]}")
    err = point2pixel(p, intrinsics, extrinsics, distortion) - px
    if reduction == "none":
        return err
    if reduction == "sum":
        return jnp.sum(jnp.abs(err), -1)
    n = safe_norm(err)
    return n if reduction == "norm" else jnp.mean(n, -1)


def bal_project(points: Any, cameras: Any) -> Array:
    """Bundle Adjustment in the Large camera model: points (..., 3), cameras (..., 9)
    = ``[r(3) Rodrigues, t(3), f, k1, k2]`` → pixels (..., 2).

    As in the BAL format: ``P = R(r) X + t``, ``p = −P[:2] / P[2]`` (the camera looks
    down −Z), ``p' = f · (1 + k1 |p|² + k2 |p|⁴) · p``; not finite for a point at depth 0
    (as the BAL solver's residuals). Batch axes broadcast."""
    fn = "bal_project"
    x = as_float_array(points, f"{fn}(points)")
    check_last_dim(x, 3, f"{fn}(points)", "[x, y, z]")
    c = as_float_array(cameras, f"{fn}(cameras)")
    check_last_dim(c, 9, f"{fn}(cameras)", "[rx, ry, rz, tx, ty, tz, f, k1, k2]")
    batch_shape(x.shape[:-1], c.shape[:-1], names=("points", "cameras"))
    return _bal(x, c)


@jax.jit
@full_precision
def _bal(x: Array, c: Array) -> Array:
    pc = SO3.exp(c[..., :3]).act(x) + c[..., 3:6]
    p = -pc[..., :2] / pc[..., 2:]  # the model's division: not finite at depth 0
    r2 = jnp.sum(p * p, -1, keepdims=True)
    k1, k2, f = c[..., 7:8], c[..., 8:9], c[..., 6:7]
    return f * (1.0 + r2 * (k1 + k2 * r2)) * p


def intrinsics_matrix(fx: Any, fy: Any, cx: Any, cy: Any, skew: Any = 0.0) -> Array:
    """K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (..., 3, 3) from broadcastable scalars."""
    fx, fy, cx, cy, s = jnp.broadcast_arrays(*(jnp.asarray(v, jnp.result_type(float))
                                               for v in (fx, fy, cx, cy, skew)))
    o, one = jnp.zeros_like(fx), jnp.ones_like(fx)
    return jnp.stack([jnp.stack([fx, s, cx], -1), jnp.stack([o, fy, cy], -1),
                      jnp.stack([o, o, one], -1)], -2)


__all__ = [
    "bal_project", "cart2homo", "homo2cart", "intrinsics_matrix", "pixel2point",
    "point2pixel", "radial_distort", "reprojerr",
]

