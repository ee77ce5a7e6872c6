"""IMU + GPS fusion as a sparse factor graph (GTSAM ``ImuFactorsExample``-style, batch).

Keyframes sit at the start of the stream and at every GPS fix. Between consecutive
keyframes the IMU samples are preintegrated (windows of equal length in one batched
call); the graph holds one pose (SE3), velocity and bias per keyframe, with

* an :func:`~jaxpose.imu.imu_factor` per window,
* a :func:`~jaxpose.imu.gps_factor` per fix,
* a :func:`~jaxpose.imu.bias_walk_factor` per window,
* priors on the first pose, velocity and bias,

and is solved with :func:`jaxpose.graph.solve` (Levenberg–Marquardt), starting from dead
reckoning with zero bias (which is also returned, for comparison).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import numpy_field
from .._precision import full_precision
from ..graph import Factor, FactorGraph, GraphSolution, solve
from ..graph._factor import vector_prior_residual
from ..lie import SE3
from ._checks import check_samples
from ._factors import bias_walk_factor, gps_factor, imu_factor, pose_prior_factor
from ._preintegration import Preintegrated, dead_reckon, preintegrate
from ._state import NavState

Array = jax.Array


class FusionResult(NamedTuple):
    """``pose`` SE3 (K,), ``vel`` (K, 3), ``bias`` (K, 6) ``[b_g, b_a]``: the fused
    keyframe states; ``keyframes`` (K,): IMU samples before each keyframe;
    ``dead_reckoning``: :class:`NavState` (K,) from the IMU alone (zero bias);
    ``solution``: the solver's :class:`~jaxpose.graph.GraphSolution`; ``graph``."""

    pose: SE3
    vel: Array
    bias: Array
    keyframes: np.ndarray
    dead_reckoning: NavState
    solution: GraphSolution
    graph: FactorGraph


@full_precision
def preintegrate_windows(
    gyro: Any, acc: Any, dt: Any, bounds: Any, **kwargs: Any
) -> Preintegrated:
    """Preintegrate the windows ``[bounds[k], bounds[k+1])`` of one sample stream
    (gyro, acc (N, 3), dt scalar or (N,)); windows of equal length share one batched
    call. Returns a :class:`Preintegrated` of batch (len(bounds) − 1,); ``kwargs`` go to
    :func:`preintegrate`."""
    fn = "preintegrate_windows"
    g, a, d, batch, _ = check_samples(gyro, acc, dt, fn)
    if batch or d.ndim > 1:
        raise ValueError(f"{fn}(gyro, acc, dt): expected one stream, gyro and acc (N, 3) "
                         f"and dt scalar or (N,), got shapes {tuple(g.shape)}, "
                         f"{tuple(a.shape)} and {tuple(d.shape)}")
    n = g.shape[0]
    b = numpy_field(bounds, np.int64, (None,), f"{fn}(bounds)")
    if b.size < 2 or np.any(np.diff(b) <= 0) or b[0] < 0 or b[-1] > n:
        raise ValueError(f"{fn}(bounds): expected increasing sample "
                         f"indices in [0, {n}] (at least two), got {b.tolist()[:8]}...")
    lengths = np.diff(b)
    parts, order = [], []
    for length in np.unique(lengths):
        sel = np.flatnonzero(lengths == length)
        idx = b[sel][:, None] + np.arange(length)[None, :]  # (w, L)
        parts.append(preintegrate(*_windows(g, a, d, idx), **kwargs))
        order.append(sel)
    return _in_order(parts, np.argsort(np.concatenate(order)))


# one compiled program each (op by op: a gather per input and length, a concatenation
# and a gather per output leaf, ~40 tiny XLA compilations per call)
@jax.jit
def _windows(g: Array, a: Array, dt: Array, idx: Any) -> tuple[Array, Array, Array]:
    d = jnp.broadcast_to(dt, g.shape[:1])
    return g[idx], a[idx], d[idx]


@jax.jit
def _in_order(parts: list[Any], inv: Any) -> Any:
    return jax.tree.map(lambda *xs: jnp.concatenate(xs, 0)[inv], *parts)


class _FusionOptions(NamedTuple):
    """The noise and prior options of :func:`fuse_imu_gps` (and of
    :func:`jaxpose.smoothing.examples.imu_gps_steps`), defaults from GTSAM's
    ``ImuFactorsExample`` (see :func:`fuse_imu_gps` for their meaning)."""

    gravity: Any = (0.0, 0.0, 0.0)
    gyro_noise: float = 2.05689024915e-4
    acc_noise: float = 3.924e-4
    integration_noise: float = 1e-4
    gyro_walk: float = 1.454441043e-6
    acc_walk: float = 4.905e-3
    gps_sigma: float = 1.0
    prior_sigmas: tuple[float, float, float, float] = (0.01, 0.5, 0.1, 1e-3)


_DEFAULTS = _FusionOptions()


def _fusion_options(fn: str, options: dict[str, Any]) -> _FusionOptions:
    """``options`` (keyword arguments of ``fn``) over the defaults; unknown names raise."""
    unknown = sorted(set(options) - set(_FusionOptions._fields))
    if unknown:
        raise TypeError(
            f"{fn}: unexpected keyword arguments {unknown}; expected some of "
            f"{list(_FusionOptions._fields)}"
        )
    opts = _DEFAULTS._replace(**options)
    for name, shapes in (("gyro_walk", [()]), ("acc_walk", [()]), ("gps_sigma", [(), (3,)]),
                         ("prior_sigmas", [(4,)])):  # the noise options are checked later
        value = np.asarray(getattr(opts, name), dtype=np.float64)
        if value.shape not in shapes or not np.all((value > 0) & np.isfinite(value)):
            raise ValueError(f"{fn}({name}): expected positive finite σ of shape "
                             f"{' or '.join(map(str, shapes))}, got {getattr(opts, name)!r}")
    return opts


def _gps_keyframes(
    fn: str, gyro: Any, acc: Any, dt: Any, gps_index: Any, gps_position: Any, init: Any,
    opts: _FusionOptions,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, Array, Preintegrated]:
    """Checked IMU + GPS stream (errors name ``fn``): ``(keyframes, gps_index, z,
    gravity, pre)`` with keyframes (K,) (sample 0 and every fix: IMU samples before
    each), the fixes' sample counts (F,) and positions (F, 3), gravity (3,) and the
    K − 1 windows between keyframes preintegrated with the options' noise."""
    if not isinstance(init, NavState):
        raise TypeError(f"{fn}(init): expected NavState, got {type(init).__name__}")
    n = jnp.shape(gyro)[0]
    gi = numpy_field(np.atleast_1d(gps_index), np.int64, (None,), f"{fn}(gps_index)")
    z = np.asarray(gps_position, dtype=np.float64)
    if z.shape != (gi.size, 3):
        raise ValueError(f"{fn}: {gi.size} GPS indices but gps_position has shape {z.shape}")
    if not np.all(np.isfinite(z)):
        raise ValueError(f"{fn}(gps_position): contains NaN or inf")
    if gi.size == 0 or np.any(np.diff(gi) < 0) or gi[0] < 0 or gi[-1] > n:
        raise ValueError(f"{fn}(gps_index): expected non-decreasing sample counts in [0, {n}]")
    keyframes = np.unique(np.concatenate([[0], gi]))
    if keyframes.size < 2:
        raise ValueError(f"{fn}(gps_index): expected a fix after sample 0 (fixes at sample 0 "
                         f"only leave no IMU window to fuse), got {gi.tolist()}")
    if jnp.shape(acc) != jnp.shape(gyro):
        raise ValueError(f"{fn}(gyro, acc): expected the same shape (N, 3), got "
                         f"{tuple(jnp.shape(gyro))} and {tuple(jnp.shape(acc))}")
    pre = preintegrate_windows(gyro, acc, dt, keyframes, gyro_noise=opts.gyro_noise,
                               acc_noise=opts.acc_noise,
                               integration_noise=opts.integration_noise)
    return keyframes, gi, z, jnp.asarray(opts.gravity, pre.vel.dtype), pre


def fuse_imu_gps(
    gyro: Any,
    acc: Any,
    dt: Any,
    gps_index: Any,
    gps_position: Any,
    init: NavState,
    *,
    gravity: Any = _DEFAULTS.gravity,
    gyro_noise: float = _DEFAULTS.gyro_noise,
    acc_noise: float = _DEFAULTS.acc_noise,
    integration_noise: float = _DEFAULTS.integration_noise,
    gyro_walk: float = _DEFAULTS.gyro_walk,
    acc_walk: float = _DEFAULTS.acc_walk,
    gps_sigma: float = _DEFAULTS.gps_sigma,
    prior_sigmas: tuple[float, float, float, float] = _DEFAULTS.prior_sigmas,
    **solve_kwargs: Any,
) -> FusionResult:
    """Fuse an IMU stream with GPS position fixes (module docstring).

    Args:
        gyro, acc: (N, 3) samples; dt: scalar or (N,) seconds.
        gps_index: (K,) number of IMU samples received before each fix (non-decreasing).
        gps_position: (K, 3) fixes in the navigation frame.
        init: the state before the first sample (also the prior mean of keyframe 0).
        gravity: navigation-frame gravity (GTSAM's example stream: zero).
        gyro_noise, acc_noise, integration_noise: σ of :func:`preintegrate`.
        gyro_walk, acc_walk: bias random-walk densities (:func:`bias_walk_factor`).
        gps_sigma: fix noise σ [m].
        prior_sigmas: σ of the priors on keyframe 0: rotation [rad], position [m],
            velocity [m/s], bias. Defaults: GTSAM's ``ImuFactorsExample``.
        solve_kwargs: passed to :func:`jaxpose.graph.solve`.
    """
    opts = _FusionOptions(gravity, gyro_noise, acc_noise, integration_noise, gyro_walk,
                         acc_walk, gps_sigma, prior_sigmas)
    keyframes, gi, z, grav, pre = _gps_keyframes("fuse_imu_gps", gyro, acc, dt, gps_index,
                                                 gps_position, init, opts)
    dtype = grav.dtype
    k = keyframes.size
    win = np.arange(k - 1)

    # initial values: dead reckoning with zero bias
    states = jax.jit(dead_reckon)(gyro, acc, dt, grav, init)
    full = jax.tree.map(lambda i0, s: jnp.concatenate([i0[None], s], 0), init, states)
    dr = full[keyframes]  # the state after keyframes[k] samples
    variables = {"pose": dr.pose(), "vel": dr.vel, "bias": jnp.zeros((k, 6), dtype)}

    s_rot, s_pos, s_vel, s_bias = prior_sigmas
    pose0 = init.pose()
    factors = [
        imu_factor(pre, win, win + 1, grav),
        gps_factor(z.astype(dtype), np.searchsorted(keyframes, gi), sigma=gps_sigma),
        bias_walk_factor(win, win + 1, np.asarray(pre.dt), gyro_walk, acc_walk),
        pose_prior_factor(SE3(pose0.data[None]), [0], rot_sigma=s_rot, pos_sigma=s_pos),
        Factor(vector_prior_residual, [("vel", np.zeros(1, np.int64))],
               data=jnp.asarray(init.vel)[None], name="vel_prior",
               information=np.eye(3) / s_vel**2),
        Factor(vector_prior_residual, [("bias", np.zeros(1, np.int64))],
               data=jnp.zeros((1, 6), dtype), name="bias_prior",
               information=np.eye(6) / s_bias**2),
    ]
    graph = FactorGraph(factors, variables)
    sol = solve(graph, **solve_kwargs)  # compiled per graph structure
    out = sol.variables
    return FusionResult(out["pose"], out["vel"], out["bias"], keyframes, dr, sol, graph)
