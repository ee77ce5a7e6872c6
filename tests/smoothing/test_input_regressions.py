"""Regressions for the fixed-lag smoother: step data and loop factors that used to
be accepted and give a wrong number (NaN data leaving the guess as the estimate,
truncated or out-of-range lags), and the IMU + GPS stream (integer samples, two fixes at
one keyframe)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.imu import NavState, fuse_imu_gps
from jaxpose.lie import InvalidValueError
from jaxpose.smoothing import FixedLagSmoother
from jaxpose.smoothing import examples as ex


def _motion(xp, x, d):
    return x["p"] - xp["p"]


def _unary(x, d):
    return x["p"] - d["z"]


X0, D0 = {"p": jnp.zeros(2)}, {"z": jnp.zeros(2)}


def _smoother(loops=0):
    kw = dict(loop=_motion, loop_data=D0, max_loops=loops) if loops else {}
    return FixedLagSmoother(X0, D0, window=3, motion=_motion, unary=_unary, **kw)


def test_update_rejects_bad_step_data():
    sm = _smoother()
    with pytest.raises(ValueError, match=r"update\(data\): leaf of shape \(3,\)"):
        sm.update(X0, {"z": jnp.zeros(3)})
    # NaN data: the step was not finite and the estimate silently stayed at the guess
    bad = {"z": jnp.array([jnp.nan, 1.0])}
    with pytest.raises(InvalidValueError, match=r"update\(data\): non-finite"):
        sm.update(X0, bad)
    with pytest.raises(Exception, match=r"update\(data\): non-finite"):
        jax.block_until_ready(jax.jit(FixedLagSmoother.update)(sm, X0, bad))
    # a valid update still solves: the only factor pins the state to z
    out = sm.update(X0, {"z": jnp.array([1.0, -2.0])})
    np.testing.assert_allclose(out.latest()["p"], [1.0, -2.0], atol=1e-12)


def test_update_rejects_bad_loop_factors():
    sm = _smoother(loops=1)
    ld = {"z": jnp.zeros((1, 2))}
    with pytest.raises(TypeError, match=r"update\(loop_lag\): expected integers"):
        sm.update(X0, D0, jnp.array([1.7]), jnp.array([True]), ld)  # was truncated to 1
    with pytest.raises(InvalidValueError, match=r"update\(loop_lag\).*lag >= 1"):
        sm.update(X0, D0, jnp.array([0]), jnp.array([True]), ld)  # was silently dropped
    with pytest.raises(ValueError, match=r"update\(loop_data\): leaf of shape \(2,\)"):
        sm.update(X0, D0, jnp.array([1]), jnp.array([True]), D0)
    nan = {"z": jnp.full((1, 2), jnp.nan)}
    with pytest.raises(InvalidValueError, match=r"update\(loop_data\): non-finite"):
        sm.update(X0, D0, jnp.array([1]), jnp.array([True]), nan)
    # padding of an unused slot may be anything
    sm.update(X0, D0, jnp.array([0]), jnp.array([False]), nan)


def test_imu_gps_steps_integer_samples_keep_gravity():
    """Integer samples: gravity was cast to their dtype (−9.81 → −9). At rest with zero
    specific force the predicted velocity after T seconds is g·T (closed form)."""
    z = np.zeros((4, 3), np.int64)
    steps = ex.imu_gps_steps(z, z, 1, [4], np.zeros((1, 3)), NavState.identity(),
                             gravity=(0.0, 0.0, -9.81))
    guess = steps.predict(steps.first, jax.tree.map(lambda a: a[1], steps.data))
    np.testing.assert_allclose(guess["vel"], [0.0, 0.0, -9.81 * 4], rtol=1e-15)


def test_imu_gps_steps_keeps_every_fix_at_one_keyframe():
    """Two fixes after the same sample: the second overwrote the first. The GPS cost at the
    keyframe must be Σ_i ½‖(p − z_i)/σ‖², gradient Σ_i (p − z_i)/σ² (closed form)."""
    z = np.zeros((4, 3))
    fixes = np.array([[1.0, 2.0, 3.0], [3.0, -2.0, 1.0]])
    sigma = 0.5
    steps = ex.imu_gps_steps(z, z, 0.01, [4, 4], fixes, NavState.identity(), gps_sigma=sigma)
    d = jax.tree.map(lambda a: a[1], steps.data)  # keyframe 1: no prior
    x = dict(steps.first)

    def cost(p):
        pose = x["pose"].__class__(jnp.concatenate([p, x["pose"].data[3:7]]))
        r = ex.imu_unary({**x, "pose": pose}, d)
        return 0.5 * r @ r

    p = jnp.array([0.3, -0.1, 0.7])
    np.testing.assert_allclose(jax.grad(cost)(p), ((p - fixes) / sigma**2).sum(0), atol=1e-12)


# Found by an audit (session 48): options accepted and then ignored or misread
def test_loop_factors_without_slots_are_refused():
    """With the default max_loops=0 the loop factors were silently dropped: the estimate
    was the chain's, not the weighted least-squares solution with the loop."""
    with pytest.raises(ValueError, match=r"FixedLagSmoother\(loop, loop_data\): .*max_loops"):
        FixedLagSmoother(X0, D0, window=3, motion=_motion, unary=_unary, loop=_motion,
                         loop_data=D0)
    sm = _smoother()
    with pytest.raises(ValueError, match=r"update: loop_lag, loop_valid or loop_data given"):
        sm.update(X0, D0, jnp.array([1]), jnp.array([True]), {"z": jnp.zeros((1, 2))})


@pytest.mark.parametrize("tol", [-1.0, 0.0, float("nan"), float("inf"), "1e-3", True])
def test_tolerance_must_be_positive_and_finite(tol):
    """tol=-1 or NaN made every update run to max_iterations and report max_steps."""
    with pytest.raises(ValueError, match=r"FixedLagSmoother\(tol\): expected a finite float"):
        FixedLagSmoother(X0, D0, window=3, motion=_motion, unary=_unary, tol=tol)


@pytest.mark.parametrize("option, value", [
    ("gps_sigma", -0.5), ("gps_sigma", 0.0), ("gps_sigma", (1.0, 2.0)),
    ("prior_sigmas", (-0.01, -0.5, -0.1, -1e-3)), ("prior_sigmas", (0.1, 0.1, 0.1)),
    ("gyro_walk", -1e-3), ("acc_walk", float("nan")),
])
def test_imu_gps_steps_refuses_what_fuse_imu_gps_refuses(option, value):
    """A negative σ acted as |σ| (it is squared in the cost) and σ = 0 put inf into the
    step data; fuse_imu_gps, whose factors these steps reproduce, raises for each."""
    z = np.zeros((4, 3))
    with pytest.raises(ValueError, match=rf"imu_gps_steps\({option}\): expected positive"):
        ex.imu_gps_steps(z, z, 0.01, [4], np.zeros((1, 3)), NavState.identity(),
                         **{option: value})


def test_fusion_errors_name_the_users_arguments():
    z = np.zeros((4, 3))
    for fn in (ex.imu_gps_steps, fuse_imu_gps):
        with pytest.raises(ValueError, match=r"\(gps_index\): expected a fix after sample 0"):
            fn(z, z, 0.01, [0], np.zeros((1, 3)), NavState.identity())
        with pytest.raises(ValueError, match=r"\(gyro, acc\): expected the same shape"):
            fn(z, z[:3], 0.01, [3], np.zeros((1, 3)), NavState.identity())
