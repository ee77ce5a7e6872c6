"""Ready-made streams for :class:`~jaxpose.smoothing.FixedLagSmoother`.

* IMU + GPS (GTSAM's ``ImuFactorsExample`` stream, :func:`imu_gps_steps`): one state
  ``{"bias": (6,) [b_g, b_a], "pose": SE3, "vel": (3,)}`` per keyframe (the start and
  every GPS fix), the factors of :func:`jaxpose.imu.fuse_imu_gps`: a preintegrated
  :func:`~jaxpose.imu.imu_residual` and a bias random walk between consecutive
  keyframes (``motion``), a GPS position fix and, on the first keyframe, priors on pose,
  velocity and bias (``unary``). New states start from :func:`~jaxpose.imu.predict` of
  the latest estimate with its bias.
* 2D pose-graph replay (:func:`pose_graph_steps`): pose ``k`` arrives with its edges to
  older poses; the edge ``(k−1, k)`` is the motion factor, the others are loop factors,
  kept while their older pose is in the window and dropped otherwise. Pose 0 carries a
  prior (σ = 1e-3) that fixes the gauge.

:func:`run` replays a stream with ``lax.scan`` (one compilation) and returns the newest
estimate and its marginal covariance at every step, and each state's last estimate
before it was marginalised (the smoother's final trajectory).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..graph._factor import _sqrt_information, between_residual
from ..imu._factors import ImuFactorData, imu_residual, pose_prior_residual
from ..imu._fusion import _fusion_options, _gps_keyframes
from ..imu._state import NavState
from ..lie import SE2, SE3, SO3
from ._fixed_lag import FixedLagSmoother, _take

Array = jax.Array

__all__ = [
    "RunResult",
    "Steps",
    "imu_gps_smoother",
    "imu_gps_steps",
    "imu_motion",
    "imu_unary",
    "pose_graph_smoother",
    "pose_graph_steps",
    "run",
    "run_scan",
    "se2_between",
    "se2_loop",
    "se2_prior",
]


class Steps(NamedTuple):
    """A stream: ``data`` step data stacked over T steps (leading axis), ``first`` the
    initial value of the first state, ``loops`` (lag (T, M), valid (T, M), data (T, M, ...))
    or None, ``predict(state, data) -> guess`` of the next state."""

    data: Any
    first: Any
    loops: Any
    predict: Callable[[Any, Any], Any]


# ---------------------------------------------------------------------- IMU + GPS
def imu_motion(xp: dict, x: dict, d: dict) -> Array:
    """Whitened ``[S_imu·r_imu (9,), S_walk·(b_j − b_i) (6,)]`` between keyframes."""
    r = imu_residual(xp["pose"], xp["vel"], x["pose"], x["vel"], xp["bias"], d["imu"])
    return jnp.concatenate([d["imu_sqrt"] @ r, d["walk_sqrt"] @ (x["bias"] - xp["bias"])])


def imu_unary(x: dict, d: dict) -> Array:
    """Whitened ``[S_gps·(t − z) (3,), w·S_prior·[pose, vel, bias prior] (15,)]``."""
    gps = d["gps_sqrt"] @ (x["pose"].data[0:3] - d["gps"])
    prior = jnp.concatenate(
        [pose_prior_residual(x["pose"], SE3(d["prior_pose"])), x["vel"] - d["prior_vel"], x["bias"]]
    )
    return jnp.concatenate([gps, d["prior_w"] * (d["prior_sqrt"] @ prior)])


def _imu_predict(gravity: Array) -> Callable[[dict, dict], dict]:
    """Next keyframe from the latest estimate: :func:`jaxpose.imu.predict`'s formulas with
    the deltas bias-corrected to first order at the estimate's bias."""

    def guess(x: dict, d: dict) -> dict:
        imu = d["imu"]
        db = imu.jac @ (x["bias"] - imu.bias_hat)
        drot = SO3(imu.rot) @ SO3.exp(db[0:3])
        dv, dp = imu.vel + db[3:6], imu.pos + db[6:9]
        rot = SO3(x["pose"].data[3:7])
        pos, vel, t = x["pose"].data[0:3], x["vel"], imu.dt
        vel_j = vel + gravity * t + rot @ dv
        pos_j = pos + vel * t + 0.5 * gravity * t * t + rot @ dp
        pose = SE3(jnp.concatenate([pos_j, (rot @ drot).data]))
        return {"bias": x["bias"], "pose": pose, "vel": vel_j}

    return guess


def imu_gps_steps(
    gyro: Any, acc: Any, dt: Any, gps_index: Any, gps_position: Any, init: NavState,
    **options: Any,
) -> Steps:
    """The IMU + GPS stream as smoother steps: arguments and keyword ``options``
    (``gravity``, ``gyro_noise``, ``acc_noise``, ``integration_noise``, ``gyro_walk``,
    ``acc_walk``, ``gps_sigma``, ``prior_sigmas``) as :func:`jaxpose.imu.fuse_imu_gps`,
    whose factors and defaults it reproduces. Keyframes: sample 0 and every fix."""
    opts = _fusion_options("imu_gps_steps", options)
    keyframes, gi, z, grav, pre = _gps_keyframes(
        "imu_gps_steps", gyro, acc, dt, gps_index, gps_position, init, opts
    )
    t = keyframes.size
    dtype = grav.dtype
    # step k >= 1 carries window k-1 -> k; step 0 a copy of window 0 (motion unused)
    idx = np.concatenate([[0], np.arange(t - 1)])
    imu = ImuFactorData(
        rot=pre.rot.data[idx],
        vel=pre.vel[idx],
        pos=pre.pos[idx],
        dt=pre.dt[idx],
        jac=pre.jac[idx],
        bias_hat=jnp.concatenate([pre.gyro_bias, pre.acc_bias], -1)[idx],
        gravity=jnp.broadcast_to(grav, (t, 3)),
    )
    cov = np.asarray(pre.cov, np.float64)[idx]
    imu_sqrt = _sqrt_information(np.linalg.inv(0.5 * (cov + np.swapaxes(cov, 1, 2))), t)
    var = np.concatenate([np.full(3, opts.gyro_walk**2), np.full(3, opts.acc_walk**2)])
    dts = np.asarray(pre.dt, np.float64)[idx]
    walk_sqrt = np.zeros((t, 6, 6))
    walk_sqrt[:, np.arange(6), np.arange(6)] = 1.0 / np.sqrt(var[None] * dts[:, None])
    gps = np.zeros((t, 3))
    gps_sqrt = np.zeros((t, 3, 3))
    # fixes at one keyframe (equal gps_index) are one factor on their mean with the
    # summed information: the same cost up to a constant as one factor each
    kf = np.searchsorted(keyframes, gi)
    count = np.bincount(kf, minlength=t)
    np.add.at(gps, kf, z)
    has = count > 0
    gps[has] /= count[has, None]
    gps_sqrt[has] = np.sqrt(count[has])[:, None, None] * np.eye(3) / opts.gps_sigma
    s_rot, s_pos, s_vel, s_bias = opts.prior_sigmas
    prior_sqrt = np.diag(
        1.0
        / np.concatenate(
            [np.full(3, s_pos), np.full(3, s_rot), np.full(3, s_vel), np.full(6, s_bias)]
        )
    )
    first = np.zeros(t)
    first[0] = 1.0
    pose0 = init.pose().data
    data = {
        "imu": imu,
        "imu_sqrt": jnp.asarray(imu_sqrt, dtype),
        "walk_sqrt": jnp.asarray(walk_sqrt, dtype),
        "gps": jnp.asarray(gps, dtype),
        "gps_sqrt": jnp.asarray(gps_sqrt, dtype),
        "prior_w": jnp.asarray(first, dtype),
        "prior_pose": jnp.broadcast_to(pose0.astype(dtype), (t, 7)),
        "prior_vel": jnp.broadcast_to(jnp.asarray(init.vel, dtype), (t, 3)),
        "prior_sqrt": jnp.broadcast_to(jnp.asarray(prior_sqrt, dtype), (t, 15, 15)),
    }
    x0 = {"bias": jnp.zeros(6, dtype), "pose": init.pose(), "vel": jnp.asarray(init.vel, dtype)}
    return Steps(data, x0, None, _imu_predict(grav))


def imu_gps_smoother(steps: Steps, window: int, **kwargs: Any) -> FixedLagSmoother:
    """An empty :class:`FixedLagSmoother` for :func:`imu_gps_steps` (``kwargs`` go to it)."""
    return _empty_smoother(steps, window, imu_motion, imu_unary, **kwargs)


def _empty_smoother(
    steps: Steps, window: int, motion: Callable, unary: Callable, **kwargs: Any
) -> FixedLagSmoother:
    """A :class:`FixedLagSmoother` with the stream's first state and step-0 data."""
    return FixedLagSmoother(
        steps.first, _take(steps.data, 0), window=window, motion=motion, unary=unary, **kwargs
    )


# ---------------------------------------------------------------------- 2D pose graph
def se2_between(xp: dict, x: dict, d: dict) -> Array:
    """Whitened ``S·Log(Z⁻¹·X_{k−1}⁻¹·X_k)`` of the odometry edge."""
    return d["sqrt"] @ between_residual(xp["pose"], x["pose"], SE2(d["z"]))


def se2_loop(xo: dict, x: dict, d: dict) -> Array:
    """Whitened loop-closure residual (same form as :func:`se2_between`)."""
    return d["sqrt"] @ between_residual(xo["pose"], x["pose"], SE2(d["z"]))


def se2_prior(x: dict, d: dict) -> Array:
    """Whitened prior ``w·Log(Z⁻¹·X)/σ`` (only on the first pose: ``w = 1``)."""
    r = SE2(d["prior"]).inv().compose(x["pose"]).log().data
    return d["prior_w"] * r / 1e-3


def _se2_predict(x: dict, d: dict) -> dict:
    return {"pose": x["pose"] @ SE2(d["z"])}


def pose_graph_steps(graph: Any, *, num_poses: int | None = None, dtype: Any = None) -> Steps:
    """Replay a 2D :class:`~jaxpose.io.PoseGraph` (first ``num_poses`` poses): step k adds
    pose k, its edge from pose k−1 (motion; an identity factor of zero weight when absent)
    and its other edges to older poses (loop factors, oriented older → k)."""
    if getattr(graph, "kind", None) != "SE2":
        raise ValueError("pose_graph_steps(graph): expected a 2D (SE2) PoseGraph")
    n = graph.poses.shape[0] if num_poses is None else int(num_poses)
    if not 2 <= n <= graph.poses.shape[0]:
        raise ValueError(
            f"pose_graph_steps(num_poses): expected 2..{graph.poses.shape[0]}, got {num_poses}"
        )
    dtype = jnp.result_type(float) if dtype is None else dtype
    e = np.asarray(graph.edges)
    zm = np.asarray(graph.measurements, np.float64)
    sq = np.asarray(_sqrt_information(graph.information, e.shape[0]))
    lo, hi = e.min(1), e.max(1)
    flip = e[:, 0] > e[:, 1]
    # orient every edge older -> newer: Z⁻¹ for flipped edges, whose residual is
    # −Ad(Z)·r, so the square-root information becomes −S·Ad(Z⁻¹)
    zs = SE2(jnp.asarray(zm)).normalize()
    zinv = zs.inv()
    z = np.where(flip[:, None], np.asarray(zinv.data), np.asarray(zs.data))
    ad = np.asarray(zinv.adj_matrix())
    sq = np.where(flip[:, None, None], -np.einsum("mij,mjk->mik", sq, ad), sq)
    keep = hi < n
    odo = np.zeros((n, 4))
    odo[:, 2] = 1.0
    odo_sqrt = np.zeros((n, 3, 3))
    lists: list[list[int]] = [[] for _ in range(n)]
    for k in np.flatnonzero(keep):
        if lo[k] == hi[k] - 1 and not odo_sqrt[hi[k]].any():
            odo[hi[k]], odo_sqrt[hi[k]] = z[k], sq[k]
        elif lo[k] < hi[k]:
            lists[hi[k]].append(k)
    m = max(1, max(len(x) for x in lists))
    lag = np.ones((n, m), np.int32)
    valid = np.zeros((n, m), bool)
    lz = np.tile(np.array([0.0, 0.0, 1.0, 0.0]), (n, m, 1))
    lsq = np.zeros((n, m, 3, 3))
    for j, ks in enumerate(lists):
        for c, k in enumerate(ks):
            lag[j, c], valid[j, c], lz[j, c], lsq[j, c] = j - lo[k], True, z[k], sq[k]
    prior_w = np.zeros(n)
    prior_w[0] = 1.0
    p0 = np.asarray(SE2(jnp.asarray(graph.poses[0], jnp.float64)).normalize().data)
    data = {
        "z": jnp.asarray(odo, dtype),
        "sqrt": jnp.asarray(odo_sqrt, dtype),
        "prior": jnp.broadcast_to(jnp.asarray(p0, dtype), (n, 4)),
        "prior_w": jnp.asarray(prior_w, dtype),
    }
    loops = (
        jnp.asarray(lag),
        jnp.asarray(valid),
        {"z": jnp.asarray(lz, dtype), "sqrt": jnp.asarray(lsq, dtype)},
    )
    x0 = {"pose": SE2(jnp.asarray(p0, dtype))}
    return Steps(data, x0, loops, _se2_predict)


def pose_graph_smoother(steps: Steps, window: int, **kwargs: Any) -> FixedLagSmoother:
    """An empty :class:`FixedLagSmoother` for :func:`pose_graph_steps`."""
    lag, _, ld = steps.loops
    return _empty_smoother(
        steps,
        window,
        se2_between,
        se2_prior,
        loop=se2_loop,
        loop_data=_take(_take(ld, 0), 0),
        max_loops=lag.shape[1],
        **kwargs,
    )


# ---------------------------------------------------------------------- runner
class RunResult(NamedTuple):
    """``latest`` stacked newest estimates (T, ...) after each step, ``latest_cov`` (T, d, d)
    their marginal covariances (None unless asked), ``trajectory`` (T, ...) each state's
    last estimate in the window, ``guesses`` (T, ...) the initial values fed, ``smoother``
    the final smoother, ``iterations`` (T,) Gauss–Newton iterations per step, ``status``
    (T,) each update's :class:`~jaxpose.results.Results` code (``FixedLagSmoother.status``)."""

    latest: Any
    latest_cov: Any
    trajectory: Any
    guesses: Any
    smoother: FixedLagSmoother
    iterations: Array
    status: Array


def _scan_impl(sm: FixedLagSmoother, steps: Steps, covariance: bool):
    def body(s, inp):
        k, d, lp = inp
        x = jax.tree.map(
            lambda a, b: jnp.where(k == 0, a, b), steps.first, steps.predict(s.latest(), d)
        )
        if lp is None:
            s = s.update(x, d)
        else:
            s = s.update(x, d, *lp)
        cov = s.marginal_covariances()[-1] if covariance else None
        return s, (s.latest(), cov, _take(s.states, 0), x, s.iterations, s.status)

    t = jax.tree.leaves(steps.data)[0].shape[0]
    sm, out = jax.lax.scan(body, sm, (jnp.arange(t), steps.data, steps.loops))
    return sm, out


_scan = eqx.filter_jit(_scan_impl)


def run_scan(sm: FixedLagSmoother, steps: Steps) -> FixedLagSmoother:
    """The smoother after replaying ``steps`` (pure: jit it, vmap it over streams)."""
    return _scan_impl(sm, steps, False)[0]


def run(sm: FixedLagSmoother, steps: Steps, *, covariance: bool = False) -> RunResult:
    """Replay ``steps`` through ``sm`` in one ``lax.scan``; see :class:`RunResult`."""
    sm, (latest, cov, oldest, guesses, its, status) = _scan(sm, steps, covariance)
    t, k = jax.tree.leaves(steps.data)[0].shape[0], sm.window
    # state j leaves the window after step j + K - 1 (its estimate in slot 0 then)
    head = _take(oldest, jnp.arange(k - 1, t)) if t >= k else None
    n_tail = min(t, k)
    tail = _take(sm.states, jnp.arange(k - n_tail, k))
    traj = (
        tail
        if head is None
        else jax.tree.map(lambda a, b: jnp.concatenate([a[: t - n_tail], b]), head, tail)
    )
    return RunResult(latest, cov, traj, guesses, sm, its, status)
