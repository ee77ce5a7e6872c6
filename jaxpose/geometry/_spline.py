"""Splines: cumulative cubic B-spline on SE3 and cubic Hermite spline on points.

Cumulative cubic B-spline (Sommer et al. 2020; Lovegrove et al. 2013; PyPose's
``bspline``): control poses C₀…C_{N−1} on uniform knots; at spline time t ∈ [0, N−3],
with segment s = ⌊t⌋ (the last segment includes t = N−3) and u = t − s,

    T(t) = C_s · Π_{j=1}^{3} Exp(B̃_j(u) · Log(C_{s+j−1}⁻¹ C_{s+j})),
    B̃(u) = (1/6) [[6, 0, 0, 0], [5, 3, −3, 1], [1, 3, 3, −2], [0, 0, 0, 1]] · [1, u, u², u³].

It is C² in t (on SE3: the pose, its body velocity and acceleration are continuous) and
does not pass through its control poses; :func:`bspline_se3_fit` finds control poses
whose spline *interpolates* given poses at t = 0, 1, …, N−1.

Cubic Hermite (:func:`hermite`): piecewise cubic through points at (possibly non-uniform)
knot times with tangents (by default the average of the adjacent secants, one-sided at the
ends, as PyPose's ``chspline``); C¹ in t and passes through every point.

:func:`bspline` and :func:`chspline` are PyPose-compatible wrappers that sample at a
fixed ``interval``. Everything is differentiable in the poses/points and in t.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count
from .._precision import full_precision
from .._stamps import shifted
from ..lie import SE3
from ..lie._base import as_float_array, runtime_check
from ._util import Array, batch_shape, check_group, points_array

_CUMULATIVE = np.array([[6, 0, 0, 0], [5, 3, -3, 1], [1, 3, 3, -2], [0, 0, 0, 1]],
                       dtype=np.float64) / 6.0


def _times(t: Any, fn: str, dtype: Any) -> Array:
    tt = as_float_array(t, f"{fn}(t)").astype(dtype)
    if tt.ndim == 0:
        tt = tt[None]
    return tt


def _segment(t: Array, n_segments: int) -> tuple[Array, Array]:
    """Segment index (int32, clipped to [0, n_segments−1]) and local u = t − s."""
    s = jnp.clip(jnp.floor(jax.lax.stop_gradient(t)), 0, n_segments - 1).astype(jnp.int32)
    return s, t - s.astype(t.dtype)


def bspline_se3(control: SE3, t: Any) -> SE3:
    """Evaluate the cumulative cubic B-spline with control poses ``control`` (..., N),
    N ≥ 4, at times ``t`` (..., M) (knot units, valid range [0, N−3]; outside it the
    end segments are extrapolated). Batch axes of ``control`` (without N) and of ``t``
    (without M) broadcast. Returns SE3 (..., M)."""
    fn = "bspline_se3"
    check_group(control, SE3, f"{fn}(control)")
    if len(control.shape) < 1 or control.shape[-1] < 4:
        raise ValueError(f"{fn}(control): expected at least 4 control poses along the last "
                         f"batch axis, got batch shape {control.shape}")
    tt = _times(t, fn, control.dtype)
    batch_shape(control.shape[:-1], tt.shape[:-1], names=("control", "t"))
    return SE3(_bspline_eval(control.data, tt))


@jax.jit
@full_precision
def _bspline_eval(cdata: Array, tt: Array) -> Array:
    return _bspline_at(cdata, *_segment(tt, cdata.shape[-2] - 3))


def _bspline_at(cdata: Array, s: Array, u: Array) -> Array:
    """The spline of controls (..., N, 7) in segments ``s`` (int) at local times ``u``
    (..., M) in [0, 1) (extrapolating outside)."""
    n = cdata.shape[-2]
    batch = tuple(np.broadcast_shapes(cdata.shape[:-2], u.shape[:-1]))
    data = jnp.broadcast_to(cdata, (*batch, n, 7))
    s, u = jnp.broadcast_to(s, (*batch, s.shape[-1])), jnp.broadcast_to(u, (*batch, u.shape[-1]))
    # the four control poses of each evaluation: (..., M, 4, 7)
    idx = s[..., None] + jnp.arange(4)
    ctrl = jnp.take_along_axis(data[..., None, :, :], idx[..., None], axis=-2)
    powers = jnp.stack([jnp.ones_like(u), u, u * u, u * u * u], -1)  # (..., M, 4)
    w = powers @ jnp.asarray(_CUMULATIVE.T, u.dtype)  # (..., M, 4): B̃_0..B̃_3
    out = SE3(ctrl[..., 0, :])
    for j in range(1, 4):
        omega = SE3(ctrl[..., j, :]).rminus(SE3(ctrl[..., j - 1, :]))
        out = out.compose(SE3.exp(w[..., j, None] * omega))
    return out.data


_bspline_sampled = jax.jit(full_precision(_bspline_at))


def _reflect(a: Array, b: Array) -> Array:
    """a · Exp(−Log(a⁻¹ b)) = a b⁻¹ a (the natural end condition)."""
    return SE3(a).compose(SE3(b).inv()).compose(SE3(a)).data


def bspline_se3_fit(poses: SE3, iterations: int = 20) -> SE3:
    """Control poses (..., N+2) of a cumulative cubic B-spline through ``poses`` (..., N),
    N ≥ 2: ``bspline_se3(fit, i) == poses[..., i]`` for i = 0, …, N−1.

    The end controls are the reflections C₋₁ = C₀C₁⁻¹C₀, C_N = C_{N−1}C_{N−2}⁻¹C_{N−1} (zero
    second derivative at the ends; they make the end poses exact), and the interior
    controls are found by ``iterations`` quasi-Newton sweeps: the knot residuals
    Log(T(i)⁻¹ P_i) are mapped through the inverse of the Euclidean interpolation matrix
    tridiag(1, 4, 1)/6 and applied on the right. The iteration converges to machine
    precision for trajectories whose rotation between consecutive poses is well below π;
    it is a fixed-length loop, so it differentiates."""
    fn = "bspline_se3_fit"
    check_group(poses, SE3, f"{fn}(poses)")
    if len(poses.shape) < 1 or poses.shape[-1] < 2:
        raise ValueError(f"{fn}(poses): expected at least 2 poses along the last batch axis, "
                         f"got batch shape {poses.shape}")
    iterations = check_count(iterations, f"{fn}(iterations)", minimum=0)
    return SE3(_fit(poses.data, iterations))


@functools.partial(jax.jit, static_argnums=1)
def _fit(p: Array, iterations: int) -> Array:
    n = p.shape[-2]

    def full(c: Array) -> Array:
        first = _reflect(c[..., 0, :], c[..., 1, :])
        last = _reflect(c[..., -1, :], c[..., -2, :])
        return jnp.concatenate([first[..., None, :], c, last[..., None, :]], -2)

    if n == 2:
        return full(p)
    knots = jnp.arange(1, n - 1, dtype=p.dtype)
    m = n - 2
    dtype = p.dtype
    dl = jnp.concatenate([jnp.zeros((1,), dtype), jnp.full((m - 1,), 1 / 6, dtype)])
    du = jnp.concatenate([jnp.full((m - 1,), 1 / 6, dtype), jnp.zeros((1,), dtype)])
    dd = jnp.full((m,), 4 / 6, dtype)

    def sweep(_: int, c: Array) -> Array:
        at = _bspline_eval(full(c), knots)  # (..., m, 7)
        err = SE3(p[..., 1:-1, :]).rminus(SE3(at))  # (..., m, 6)
        flat = err.reshape(-1, m, 6)
        sol = jax.vmap(lambda e: jax.lax.linalg.tridiagonal_solve(dl, dd, du, e))(flat)
        delta = sol.reshape(err.shape)
        inner = SE3(c[..., 1:-1, :]).retract(delta).data
        return jnp.concatenate([c[..., :1, :], inner, c[..., -1:, :]], -2)

    c = jax.lax.fori_loop(0, iterations, sweep, p)
    return full(c)


def hermite(points: Any, t: Any, times: Any = None, tangents: Any = None) -> Array:
    """Cubic Hermite spline through ``points`` (..., N, D), N ≥ 2, at knot ``times``
    (..., N) strictly increasing (default 0, 1, …, N−1), evaluated at ``t`` (..., M).

    ``tangents`` (..., N, D) are dp/dt at the knots; default: the mean of the adjacent
    secants (one-sided at the ends). Outside [t₀, t_{N−1}] the end cubics extrapolate.
    Returns (..., M, D). Host ``times`` and ``t`` (NumPy, lists) are shifted to a
    common origin first, so epoch seconds keep their differences in float32."""
    fn = "hermite"
    if times is not None:
        times, t = shifted(times, t)
    p = points_array(points, f"{fn}(points)", None, min_points=2)
    n = p.shape[-2]
    dtype = p.dtype
    tk = (jnp.arange(n, dtype=dtype) if times is None
          else as_float_array(times, f"{fn}(times)").astype(dtype))
    if tk.ndim < 1 or tk.shape[-1] != n:
        raise ValueError(f"{fn}(times): expected shape (..., N) with N = {n}, got shape "
                         f"{tuple(tk.shape)}")
    if times is not None:
        tk = runtime_check(tk, jnp.any(~(tk[..., 1:] > tk[..., :-1])),
                           f"{fn}(times): expected strictly increasing knot times")
    tt = _times(t, fn, dtype)
    shapes, names = [p.shape[:-2], tk.shape[:-1], tt.shape[:-1]], ["points", "times", "t"]
    if tangents is not None:
        m = as_float_array(tangents, f"{fn}(tangents)").astype(dtype)
        if m.shape[-2:] != p.shape[-2:]:
            raise ValueError(f"{fn}(tangents): expected shape (..., {n}, {p.shape[-1]}) like "
                             f"points, got {tuple(m.shape)}")
        shapes.append(m.shape[:-2])
        names.append("tangents")
    batch = batch_shape(*shapes, names=tuple(names))
    return _hermite(p, tk, tt, None if tangents is None else m, batch)


@functools.partial(jax.jit, static_argnums=4)
def _hermite(p: Array, tk: Array, tt: Array, m: Array | None, batch: tuple[int, ...]
             ) -> Array:
    n = p.shape[-2]
    p = jnp.broadcast_to(p, (*batch, *p.shape[-2:]))
    tk = jnp.broadcast_to(tk, (*batch, n))
    tt = jnp.broadcast_to(tt, (*batch, tt.shape[-1]))
    dt = tk[..., 1:] - tk[..., :-1]  # (..., N−1)
    if m is None:
        m = _secant_tangents((p[..., 1:, :] - p[..., :-1, :]) / dt[..., None])
    else:
        m = jnp.broadcast_to(m, p.shape)
    tk_sg = jax.lax.stop_gradient(tk)
    s = jax.vmap(lambda a, v: jnp.searchsorted(a, v, side="right"))(
        tk_sg.reshape(-1, n), jax.lax.stop_gradient(tt).reshape(-1, tt.shape[-1]))
    s = jnp.clip(s.reshape(tt.shape) - 1, 0, n - 2)
    take = lambda a, i: jnp.take_along_axis(a, i, axis=-1)
    h = take(dt, s)
    return _hermite_at(p, m, s, (tt - take(tk, s)) / h, h)


def _secant_tangents(sec: Array) -> Array:
    """Knot tangents (..., N, D) from the N − 1 secants: the mean of the adjacent ones,
    one-sided at the ends (:func:`hermite`'s default)."""
    mid = 0.5 * (sec[..., 1:, :] + sec[..., :-1, :])
    return jnp.concatenate([sec[..., :1, :], mid, sec[..., -1:, :]], -2)


def _hermite_at(p: Array, m: Array, s: Array, u: Array, h: Array) -> Array:
    """The cubic of knot interval ``s`` (int, (..., M)) at local time ``u`` ∈ [0, 1]
    (extrapolating outside), interval lengths ``h``; points and tangents (..., N, D)."""
    u2, u3 = u * u, u * u * u
    h00 = 2 * u3 - 3 * u2 + 1
    h10 = u3 - 2 * u2 + u
    h01 = -2 * u3 + 3 * u2
    h11 = u3 - u2
    gather = lambda a, i: jnp.take_along_axis(a, i[..., None], axis=-2)
    return (h00[..., None] * gather(p, s) + (h10 * h)[..., None] * gather(m, s)
            + h01[..., None] * gather(p, s + 1) + (h11 * h)[..., None] * gather(m, s + 1))


def _pypose_segments(n: int, interval: float, fn: str) -> tuple[np.ndarray, np.ndarray]:
    """PyPose's sample times 0, interval, …, n − 1 as (segment, local time) pairs, kept
    apart so that float32 evaluations do not round the times (at t ≈ 2e4 float32's spacing
    is 2e-3)."""
    if not 0 < interval < 1:
        raise ValueError(f"{fn}(interval): expected 0 < interval < 1, got {interval!r}")
    steps = np.arange(0, 1, interval)
    seg = np.repeat(np.arange(n - 1, dtype=np.int32), len(steps))
    u = np.tile(steps, n - 1)
    # the last sample, t = n − 1: the end of the last segment
    return np.append(seg, np.int32(n - 2)), np.append(u, 1.0)


def chspline(points: Any, interval: float = 0.1) -> Array:
    """PyPose's ``chspline``: :func:`hermite` through points (..., N, D) at unit spacing,
    sampled every ``interval`` from 0 to N−1 inclusive."""
    p = points_array(points, "chspline(points)", None, min_points=2)
    s, u = _pypose_segments(p.shape[-2], interval, "chspline")
    return _chspline(p, jnp.asarray(s), jnp.asarray(u, p.dtype))


@jax.jit
def _chspline(p: Array, s: Array, u: Array) -> Array:
    """:func:`hermite` at unit knots with the default tangents, at segments ``s`` and local
    times ``u``."""
    m = _secant_tangents(p[..., 1:, :] - p[..., :-1, :])
    s, u = (jnp.broadcast_to(a, (*p.shape[:-2], a.shape[-1])) for a in (s, u))
    return _hermite_at(p, m, s, u, jnp.ones_like(u))


def bspline(poses: SE3, interval: float = 0.1, extrapolate: bool = False) -> SE3:
    """PyPose's ``bspline``: :func:`bspline_se3` with the poses (..., N) as controls,
    sampled every ``interval`` over each of the N−3 segments plus the final end point.
    ``extrapolate=True`` pads two copies of the first and last pose (so the curve starts
    and ends at them)."""
    fn = "bspline"
    check_group(poses, SE3, f"{fn}(poses)")
    if not 0 < interval < 1:
        raise ValueError(f"{fn}(interval): expected 0 < interval < 1, got {interval!r}")
    data = poses.data
    if extrapolate:
        if len(poses.shape) < 1 or poses.shape[-1] < 1:
            raise ValueError(f"{fn}(poses): expected at least 1 pose, got {poses.shape}")
        data = jnp.concatenate([data[..., :1, :], data[..., :1, :], data,
                                data[..., -1:, :], data[..., -1:, :]], -2)
    elif len(poses.shape) < 1 or poses.shape[-1] < 4:
        raise ValueError(f"{fn}(poses): expected at least 4 poses (or extrapolate=True), "
                         f"got batch shape {poses.shape}")
    seg, u = _pypose_segments(data.shape[-2] - 2, interval, fn)
    return SE3(_bspline_sampled(data, jnp.asarray(seg), jnp.asarray(u, data.dtype)))


__all__ = ["bspline", "bspline_se3", "bspline_se3_fit", "chspline", "hermite"]
