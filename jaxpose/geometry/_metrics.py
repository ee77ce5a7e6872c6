"""Trajectory metrics: absolute and relative pose error (APE / RPE) with timestamp
association, SE3 / Sim3 alignment and the usual statistics.

Semantics follow PyPose's ``pp.metric.ape`` / ``rpe`` (which follow evo):

* association: the shorter trajectory's stamps are matched to the nearest stamp of the
  longer one (estimate stamps shifted by ``offset`` first); pairs farther apart than
  ``max_diff`` are dropped. Stamps must be ascending. Without stamps, poses are paired by
  index (equal lengths required).
* alignment of the estimate onto the reference from the associated positions: ``"se3"``
  (Kabsch) or ``"sim3"`` (Umeyama with scale), or ``"origin"`` (first associated poses
  coincide); a Sim3 (s, R, t) acts on a pose (R_e, t_e) as (R R_e, s R t_e + t).
* ``etype``: ``"translation"`` ‖t_e − t_r‖; ``"rotation"`` ‖R_Δ − I‖_F; ``"pose"``
  ‖T_Δ − I‖_F; ``"radian"`` / ``"degree"`` the angle of R_Δ; with T_Δ = T_e⁻¹ T_r (APE) or
  (T_r,i⁻¹ T_r,j)⁻¹ (T_e,i⁻¹ T_e,j) (RPE, translation error ‖t_Δ‖).
* RPE pairs frames k and k + ``delta`` of the associated sequence: every k
  (``all_pairs=True``) or k = 0, delta, 2·delta, … (PyPose's default). With
  ``pair_by="distance"`` (PyPose's ``associate='distance'``), ``delta`` is a path length
  measured along the aligned estimate (``pairs_from="est"``, PyPose's default) or the
  reference: ``all_pairs=False`` takes the frames where the path walked since the last
  chosen frame first reaches ``delta`` (consecutive such frames are paired);
  ``all_pairs=True`` pairs every frame i with the later frame whose path distance from i
  is nearest to ``delta``, kept when within ``rtol·delta`` of it.
* statistics over the valid errors: max, min, mean, median (mean of the two middle values
  for an even count, as numpy/evo; PyPose's torch.median takes the lower one), RMSE, SSE
  and the population std (numpy/evo; PyPose's torch.std divides by n − 1).

Everything has static shapes — invalid pairs are masked, not removed — so the metrics jit,
vmap and differentiate (with respect to the poses).
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_count
from .._safe import safe_norm
from .._stamps import shifted
from ..lie import SE3, Sim3
from ..lie._base import as_float_array, runtime_check
from ._registration import umeyama
from ._util import Array, check_group

_ETYPES = ("translation", "rotation", "pose", "radian", "degree")
_ALIGN = (None, "se3", "sim3", "origin")


class ErrorStats(NamedTuple):
    """Statistics of the valid errors (NaN when there are none)."""

    max: Array
    min: Array
    mean: Array
    median: Array
    rmse: Array
    sse: Array
    std: Array


class TrajectoryError(NamedTuple):
    """``errors`` (K,) per associated pose (APE) or pose pair (RPE); ``valid`` (K,) bool;
    ``stats`` :class:`ErrorStats`; ``alignment`` the Sim3 applied to the estimate
    (identity when not aligned); ``pairs`` (K, 2) int32 indices into (reference, estimate)
    for APE, or into the associated sequence for RPE."""

    errors: Array
    valid: Array
    stats: ErrorStats
    alignment: Sim3
    pairs: Array


def _broadcasts_to(shape: tuple[int, ...], target: tuple[int, ...]) -> bool:
    try:
        return np.broadcast_shapes(shape, target) == target
    except ValueError:
        return False


def _sqrt0(x: Array) -> Array:
    """√x with a zero derivative (not inf) at x = 0; NaN and inf pass through."""
    return jnp.where(x == 0, 0.0, jnp.sqrt(jnp.where(x == 0, 1.0, x)))


def error_stats(errors: Any, valid: Any = None) -> ErrorStats:
    """Max, min, mean, median, RMSE, SSE and population std over the last axis of
    ``errors`` (..., K) where ``valid`` (..., K) (default all); NaN where no entry is
    valid, and NaN/inf errors propagate as in numpy (a NaN makes every statistic NaN)."""
    e = as_float_array(errors, "error_stats(errors)")
    if e.ndim < 1:
        raise ValueError("error_stats(errors): expected shape (..., K), got a scalar")
    if e.shape[-1] == 0:
        raise ValueError(f"error_stats(errors): expected at least one error along the last "
                         f"axis, got shape {tuple(e.shape)}")
    if valid is not None and not _broadcasts_to(np.shape(valid), e.shape):
        raise ValueError(f"error_stats(valid): expected a shape that broadcasts to errors' "
                         f"{tuple(e.shape)}, got {np.shape(valid)}")
    v = jnp.ones(e.shape, bool) if valid is None else jnp.broadcast_to(
        jnp.asarray(valid, bool), e.shape)
    n = jnp.sum(v, -1)
    nf = jnp.maximum(n, 1).astype(e.dtype)
    nan = jnp.asarray(jnp.nan, e.dtype)
    z = jnp.where(v, e, 0.0)
    mean = jnp.sum(z, -1) / nf
    sse = jnp.sum(z * z, -1)
    var = jnp.sum(jnp.where(v, jnp.square(e - mean[..., None]), 0.0), -1) / nf
    std = _sqrt0(var)
    rmse = _sqrt0(sse / nf)
    # invalid entries sort last (+inf); a NaN error (sorted after them) makes the median
    # NaN, as numpy's, rather than the middle of the others
    srt = jnp.sort(jnp.where(v, e, jnp.inf), -1)
    lo = jnp.take_along_axis(srt, jnp.maximum((n - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = jnp.take_along_axis(srt, jnp.maximum(n // 2, 0)[..., None], -1)[..., 0]
    median = jnp.where(jnp.any(v & jnp.isnan(e), -1), nan, 0.5 * (lo + hi))
    out = ErrorStats(
        max=jnp.max(jnp.where(v, e, -jnp.inf), -1),
        min=jnp.min(jnp.where(v, e, jnp.inf), -1),
        mean=mean,
        median=median,
        rmse=rmse,
        sse=sse,
        std=std,
    )
    return ErrorStats(*(jnp.where(n > 0, x, nan) for x in out))


def _stamps(x: Any, n: int, argname: str, dtype: Any) -> Array:
    s = as_float_array(x, argname).astype(dtype)
    if s.shape != (n,):
        raise ValueError(f"{argname}: expected shape ({n},) (one stamp per pose), got "
                         f"{tuple(s.shape)}")
    return runtime_check(s, jnp.any(s[1:] < s[:-1]) if n > 1 else jnp.asarray(False),
                         f"{argname}: timestamps must be ascending")


def associate(
    ref_stamps: Any, est_stamps: Any, max_diff: float = 0.01, offset: float = 0.0
) -> tuple[Array, Array, Array]:
    """Match timestamps: for each stamp of the shorter sequence, the nearest stamp of the
    longer one (``est_stamps + offset`` against ``ref_stamps``).

    Returns (ref_idx (K,), est_idx (K,), valid (K,)), K = the shorter length; a pair is
    valid when the stamps differ by less than ``max_diff``. Stamps must be ascending.
    Host stamps (NumPy, lists) are shifted to a common origin before they become JAX
    arrays, so epoch seconds or nanoseconds keep their differences in float32."""
    ref_stamps, est_stamps = shifted(ref_stamps, est_stamps)
    r = as_float_array(ref_stamps, "associate(ref_stamps)")
    e = as_float_array(est_stamps, "associate(est_stamps)")
    if r.ndim != 1 or e.ndim != 1 or r.shape[0] == 0 or e.shape[0] == 0:
        raise ValueError(f"associate(ref_stamps, est_stamps): expected non-empty 1-D arrays, "
                         f"got shapes {tuple(r.shape)} and {tuple(e.shape)}")
    dtype = jnp.result_type(r.dtype, e.dtype)
    r = _stamps(r, r.shape[0], "associate(ref_stamps)", dtype)
    e = _stamps(e, e.shape[0], "associate(est_stamps)", dtype) + offset
    est_short = e.shape[0] <= r.shape[0]
    short, long = (e, r) if est_short else (r, e)
    j = jnp.clip(jnp.searchsorted(long, short), 1, long.shape[0] - 1) if long.shape[0] > 1 \
        else jnp.zeros(short.shape, jnp.int32)
    if long.shape[0] > 1:
        left = jnp.abs(short - long[j - 1])
        right = jnp.abs(short - long[j])
        j = jnp.where(left <= right, j - 1, j)
    diff = jnp.abs(short - long[j])
    valid = diff < max_diff
    i = jnp.arange(short.shape[0], dtype=jnp.int32)
    j = j.astype(jnp.int32)
    return (j, i, valid) if est_short else (i, j, valid)


def _check_trajectories(ref: Any, est: Any, ref_stamps: Any, est_stamps: Any, fn: str
                        ) -> None:
    check_group(ref, SE3, f"{fn}(ref)")
    check_group(est, SE3, f"{fn}(est)")
    if len(ref.shape) != 1 or len(est.shape) != 1 or not ref.shape[0] or not est.shape[0]:
        raise ValueError(f"{fn}(ref, est): expected non-empty 1-D trajectories (batch shape "
                         f"(N,)), got {ref.shape} and {est.shape}; vmap for batches")
    if (ref_stamps is None) != (est_stamps is None):
        raise ValueError(f"{fn}(ref_stamps, est_stamps): give both or neither")
    if ref_stamps is None:
        if ref.shape != est.shape:
            raise ValueError(f"{fn}(ref, est): without timestamps the trajectories are paired "
                             f"by index and need equal lengths, got {ref.shape[0]} and "
                             f"{est.shape[0]}")
    else:
        for arg, stamps, n in (("ref_stamps", ref_stamps, ref.shape[0]),
                               ("est_stamps", est_stamps, est.shape[0])):
            shape = np.shape(stamps)
            if shape != (n,):
                raise ValueError(f"{fn}({arg}): expected shape ({n},) (one stamp per pose), "
                                 f"got {shape}")


def _pair_poses(
    ref: SE3, est: SE3, ref_stamps: Any, est_stamps: Any, max_diff: Any, offset: Any,
) -> tuple[SE3, SE3, Array, Array]:
    if ref_stamps is None:
        n = ref.shape[0]
        ri = ei = jnp.arange(n, dtype=jnp.int32)
        valid = jnp.ones((n,), bool)
    else:
        ri, ei, valid = associate(ref_stamps, est_stamps, max_diff, offset)
    return SE3(ref.data[ri]), SE3(est.data[ei]), valid, jnp.stack([ri, ei], -1)


def _alignment(ref: SE3, est: SE3, valid: Array, align: str | None) -> Sim3:
    dtype = ref.dtype
    if align is None:
        return Sim3.identity(dtype=dtype)
    if align == "origin":
        first = jnp.argmax(valid)
        t = ref[first].compose(est[first].inv())
        return Sim3(jnp.concatenate([t.data, jnp.ones((1,), dtype)]))
    w = valid.astype(dtype)
    return umeyama(est.translation(), ref.translation(), with_scale=align == "sim3", weights=w)


def _apply(s: Sim3, poses: SE3) -> SE3:
    """(s, R, t) ∘ (R_e, t_e) = (R R_e, s R t_e + t)."""
    t = s.act(poses.translation())
    q = s.rotation().compose(poses.rotation()).data
    return SE3(jnp.concatenate([t, q], -1))


def _errors(delta: SE3, etype: str, translation_err: Array | None = None) -> Array:
    if etype == "translation":
        return safe_norm(delta.translation()) if translation_err is None else translation_err
    if etype == "rotation":
        r = delta.rotation().matrix()
        return safe_norm((r - jnp.eye(3, dtype=r.dtype)).reshape(*r.shape[:-2], 9))
    if etype == "pose":
        m = delta.matrix()
        return safe_norm((m - jnp.eye(4, dtype=m.dtype)).reshape(*m.shape[:-2], 16))
    ang = safe_norm(delta.rotation().log().data)
    return ang if etype == "radian" else jnp.rad2deg(ang)


def _check_options(fn: str, etype: str, align: str | None) -> None:
    if etype not in _ETYPES:
        raise ValueError(f"{fn}(etype): expected one of {_ETYPES}, got {etype!r}")
    if align not in _ALIGN:
        raise ValueError(f"{fn}(align): expected one of {_ALIGN}, got {align!r}")


def ape(
    ref: SE3,
    est: SE3,
    ref_stamps: Any = None,
    est_stamps: Any = None,
    *,
    etype: str = "translation",
    align: str | None = None,
    max_diff: float = 0.01,
    offset: float = 0.0,
) -> TrajectoryError:
    """Absolute pose error of the estimate ``est`` (M,) against the reference ``ref``
    (N,) (SE3 trajectories; stamps (N,), (M,) optional). See the module docstring for
    ``etype`` and ``align`` (None, ``"se3"``, ``"sim3"``, ``"origin"``)."""
    fn = "ape"
    _check_options(fn, etype, align)
    _check_trajectories(ref, est, ref_stamps, est_stamps, fn)
    if ref_stamps is not None:  # epoch seconds keep their differences in float32
        ref_stamps, est_stamps = shifted(ref_stamps, est_stamps)
    return _ape(ref.data, est.data, ref_stamps, est_stamps, max_diff, offset, etype=etype,
                align=align)


@functools.partial(jax.jit, static_argnames=("etype", "align"))
def _ape(ref: Array, est: Array, ref_stamps: Any, est_stamps: Any, max_diff: Any,
         offset: Any, *, etype: str, align: str | None) -> TrajectoryError:
    r, e, valid, pairs = _pair_poses(SE3(ref), SE3(est), ref_stamps, est_stamps, max_diff,
                                     offset)
    s = _alignment(r, e, valid, align)
    e = _apply(s, e)
    delta = e.inv().compose(r)
    trans = safe_norm(e.translation() - r.translation())
    err = _errors(delta, etype, trans)
    return TrajectoryError(err, valid, error_stats(err, valid), s, pairs)


def rpe(
    ref: SE3,
    est: SE3,
    ref_stamps: Any = None,
    est_stamps: Any = None,
    *,
    etype: str = "translation",
    delta: float = 1,
    all_pairs: bool = False,
    align: str | None = None,
    max_diff: float = 0.01,
    offset: float = 0.0,
    pair_by: str = "frame",
    rtol: float = 0.1,
    pairs_from: str = "est",
) -> TrajectoryError:
    """Relative pose error between frames ``delta`` apart (in the associated sequence).

    ``pair_by="frame"``: ``delta`` is a positive int frame count; ``all_pairs=False`` uses
    frames 0, delta, 2·delta, … (consecutive pairs of them), as PyPose; ``True`` every
    frame k with k + delta. ``pair_by="distance"``: ``delta`` > 0 is a path length (see
    the module docstring for ``rtol`` and ``pairs_from``)."""
    fn = "rpe"
    _check_options(fn, etype, align)
    if pair_by not in ("frame", "distance"):
        raise ValueError(f"{fn}(pair_by): expected 'frame' or 'distance', got {pair_by!r}")
    if pairs_from not in ("est", "ref"):
        raise ValueError(f"{fn}(pairs_from): expected 'est' or 'ref', got {pairs_from!r}")
    if pair_by == "frame":
        delta = check_count(delta, f"{fn}(delta) (a frame count)")
    if pair_by == "distance":
        if not isinstance(delta, int | float) or isinstance(delta, bool) or \
                not np.isfinite(delta) or delta <= 0:
            raise ValueError(f"{fn}(delta): expected a positive finite path length, got "
                             f"{delta!r}")
        if not isinstance(rtol, int | float) or not np.isfinite(rtol) or rtol < 0:
            raise ValueError(f"{fn}(rtol): expected a non-negative finite number, got "
                             f"{rtol!r}")
    _check_trajectories(ref, est, ref_stamps, est_stamps, fn)
    if ref_stamps is not None:  # epoch seconds keep their differences in float32
        ref_stamps, est_stamps = shifted(ref_stamps, est_stamps)
    if pair_by == "distance":
        return _rpe_distance(ref.data, est.data, ref_stamps, est_stamps, max_diff, offset,
                             float(delta), float(rtol), etype=etype, align=align,
                             all_pairs=bool(all_pairs), from_ref=pairs_from == "ref")
    return _rpe(ref.data, est.data, ref_stamps, est_stamps, max_diff, offset, etype=etype,
                align=align, delta=delta, all_pairs=bool(all_pairs))


def _relative_error(r: SE3, e: SE3, i: Array, j: Array, ok: Array, s: Sim3, etype: str
                    ) -> TrajectoryError:
    """RPE of the pairs (i, j) of the compacted, aligned sequences ``r``, ``e``."""
    rel_r = SE3(r.data[i]).inv().compose(SE3(r.data[j]))
    rel_e = SE3(e.data[i]).inv().compose(SE3(e.data[j]))
    err = _errors(rel_r.inv().compose(rel_e), etype)
    return TrajectoryError(err, ok, error_stats(err, ok), s, jnp.stack([i, j], -1))


def _aligned_compacted(ref: Array, est: Array, ref_stamps: Any, est_stamps: Any,
                       max_diff: Any, offset: Any, align: str | None
                       ) -> tuple[SE3, SE3, Array, Sim3]:
    """Associate, align, and move the valid associations to the front (stable)."""
    r, e, valid, _ = _pair_poses(SE3(ref), SE3(est), ref_stamps, est_stamps, max_diff,
                                 offset)
    s = _alignment(r, e, valid, align)
    e = _apply(s, e)
    order = jnp.argsort(~valid, stable=True)
    return SE3(r.data[order]), SE3(e.data[order]), jnp.sum(valid), s


@functools.partial(jax.jit, static_argnames=("etype", "align", "all_pairs", "from_ref"))
def _rpe_distance(ref: Array, est: Array, ref_stamps: Any, est_stamps: Any, max_diff: Any,
                  offset: Any, delta: Any, rtol: Any, *, etype: str, align: str | None,
                  all_pairs: bool, from_ref: bool) -> TrajectoryError:
    r, e, count, s = _aligned_compacted(ref, est, ref_stamps, est_stamps, max_diff, offset,
                                        align)
    k = r.shape[0]
    pos = (r if from_ref else e).translation()
    step = safe_norm(pos[1:] - pos[:-1])
    idx = jnp.arange(k, dtype=jnp.int32)
    if all_pairs:
        # path distance travelled up to each frame (non-decreasing), frames beyond the
        # valid count pushed to +inf so they are never chosen
        d = jnp.concatenate([jnp.zeros((1,), step.dtype), jnp.cumsum(step)])
        d = jnp.where(idx < count, d, jnp.inf)
        target = d + delta
        right = jnp.searchsorted(d, target, side="left").astype(jnp.int32)  # first ≥ target
        left_val = d[jnp.clip(right - 1, 0, k - 1)]
        # the first frame after i with the largest distance below the target
        left = jnp.maximum(jnp.searchsorted(d, left_val, side="left").astype(jnp.int32),
                           idx + 1)
        has_left = right - 1 > idx
        has_right = right < count
        err_l = jnp.where(has_left, jnp.abs(left_val - target), jnp.inf)
        err_r = jnp.where(has_right, jnp.abs(d[jnp.minimum(right, k - 1)] - target), jnp.inf)
        j = jnp.where(err_l <= err_r, left, right)
        ok = (idx < count) & (jnp.minimum(err_l, err_r) <= rtol * delta)
        return _relative_error(r, e, idx, jnp.minimum(j, k - 1), ok, s, etype)

    def walk(path: Array, x: tuple[Array, Array]) -> tuple[Array, Array]:
        length, live = x
        path = path + jnp.where(live, length, 0.0)
        hit = live & (path >= delta)
        return jnp.where(hit, 0.0, path), hit

    lengths = jnp.concatenate([jnp.zeros((1,), step.dtype), step])
    _, chosen = jax.lax.scan(walk, jnp.zeros((), step.dtype), (lengths, idx < count))
    order = jnp.argsort(~chosen, stable=True).astype(jnp.int32)
    n_chosen = jnp.sum(chosen)
    i, j = order, jnp.roll(order, -1)
    ok = idx + 1 < n_chosen
    return _relative_error(r, e, i, jnp.where(ok, j, i), ok, s, etype)


@functools.partial(jax.jit, static_argnames=("etype", "align", "delta", "all_pairs"))
def _rpe(ref: Array, est: Array, ref_stamps: Any, est_stamps: Any, max_diff: Any,
         offset: Any, *, etype: str, align: str | None, delta: int, all_pairs: bool
         ) -> TrajectoryError:
    r, e, count, s = _aligned_compacted(ref, est, ref_stamps, est_stamps, max_diff, offset,
                                        align)
    k = r.shape[0]
    if all_pairs:
        i = jnp.arange(k, dtype=jnp.int32)
        j = i + delta
        ok = j < count
    else:
        i = jnp.arange(0, k, delta, dtype=jnp.int32)
        j = i + delta
        ok = j < count
    return _relative_error(r, e, i, jnp.minimum(j, k - 1), ok, s, etype)


__all__ = ["ErrorStats", "TrajectoryError", "ape", "associate", "error_stats", "rpe"]

