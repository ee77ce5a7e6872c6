"""Regressions: bad input to the IMU functions that used to be accepted and give a
wrong number (truncated indices and time steps, silently mixed linearisation biases), or
fail with messages that did not name the argument."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.imu import (
    ImuPreintegrator,
    NavState,
    bias_walk_factor,
    fuse_imu_gps,
    gps_factor,
    predict,
    preintegrate,
    preintegrate_windows,
)
from jaxpose.lie import InvalidValueError

N = 10
RNG = np.random.default_rng(7)
GYRO, ACC = RNG.normal(size=(N, 3)) * 0.3, RNG.normal(size=(N, 3))


def test_preintegrate_windows_rejects_fractional_bounds():
    # [0, 4.7, 10.2] was truncated to [0, 4, 10] without a word
    with pytest.raises(ValueError, match=r"preintegrate_windows\(bounds\): expected integers"):
        preintegrate_windows(GYRO, ACC, 0.01, [0, 4.7, 10.2])
    with pytest.raises(ValueError, match=r"preintegrate_windows\(bounds\)"):
        preintegrate_windows(GYRO, ACC, 0.01, [[0, 4], [4, 10]])


def test_preintegrate_windows_integer_samples_keep_fractional_dt():
    """Integer samples: dt = 1.5 was cast to the samples' integer dtype (1). At rest with a
    constant specific force a: Δt = n·dt, Δv = a·Δt, Δp = ½·a·Δt² (closed form)."""
    zero, acc = np.zeros((N, 3), np.int64), np.tile(np.array([1, -2, 3], np.int64), (N, 1))
    pre = preintegrate_windows(zero, acc, 1.5, [0, 4, 10])
    t = np.array([4 * 1.5, 6 * 1.5])
    np.testing.assert_allclose(pre.dt, t, rtol=1e-15)
    np.testing.assert_allclose(pre.vel, t[:, None] * [1, -2, 3], rtol=1e-14)
    np.testing.assert_allclose(pre.pos, 0.5 * t[:, None] ** 2 * [1, -2, 3], rtol=1e-14)


@pytest.mark.parametrize("gyro, dt", [
    (GYRO, np.full(N - 1, 0.01)),  # one step short: an unnamed broadcasting error
    (GYRO, np.full(1, 0.01)),  # one step for N samples: silently broadcast
    (np.stack([GYRO, GYRO]), 0.01),  # two streams: windows cut along the wrong axis
])
def test_preintegrate_windows_checks_sample_shapes(gyro, dt):
    with pytest.raises(ValueError, match=r"preintegrate_windows\((gyro|dt)"):
        preintegrate_windows(gyro, np.broadcast_to(ACC, gyro.shape), dt, [0, 1, 2])


@pytest.mark.parametrize("index, position, match", [
    ([4.6, 9.2], np.zeros((2, 3)), r"fuse_imu_gps\(gps_index\): expected integers"),
    ([[4, 9]], np.zeros((2, 3)), r"fuse_imu_gps\(gps_index\): expected shape"),
    ([4, 9], [[0, 0, 0], [np.nan, 0, 0]], r"fuse_imu_gps\(gps_position\): contains NaN"),
])
def test_fuse_rejects_bad_fixes(index, position, match):
    with pytest.raises(ValueError, match=match):
        fuse_imu_gps(GYRO, ACC, 0.01, index, position, NavState.identity())


def _windows(**kw):
    kw = dict(gyro_noise=0.1, acc_noise=0.2, **kw)
    return (preintegrate(GYRO[:5], ACC[:5], 0.01, **kw),
            preintegrate(GYRO[5:], ACC[5:], 0.01, **kw))


def test_compose_rejects_different_linearisation_biases():
    """Composing windows preintegrated at different biases returned the first window's
    biases with Jacobians taken at two different points."""
    a, _ = _windows(gyro_bias=[0.1, 0.0, 0.0])
    _, b = _windows(gyro_bias=[0.2, 0.0, 0.0])
    with pytest.raises(InvalidValueError, match="different linearisation biases"):
        a.compose(b)
    with pytest.raises(Exception, match="different linearisation biases"):
        jax.block_until_ready(jax.jit(lambda p, q: (p @ q).pos)(a, b))
    a, b = _windows(acc_bias=[0.0, 0.1, 0.0])
    whole = preintegrate(GYRO, ACC, 0.01, gyro_noise=0.1, acc_noise=0.2, acc_bias=[0, 0.1, 0])
    np.testing.assert_allclose((a @ b).jac, whole.jac, atol=1e-15)


def test_predict_broadcasts_a_batch_of_gyro_biases():
    """A (2, 3) gyro bias with no accelerometer bias failed inside a concatenation."""
    pre = preintegrate(GYRO, ACC, 0.01)
    bg = np.array([[0.01, 0.0, 0.0], [0.0, -0.02, 0.01]])
    out = predict(NavState.identity(), pre, [0, 0, -9.81], gyro_bias=bg)
    for k in range(2):
        one = predict(NavState.identity(), pre, [0, 0, -9.81], gyro_bias=bg[k], acc_bias=[0, 0, 0])
        np.testing.assert_allclose(out.pos[k], one.pos, atol=1e-15)
        np.testing.assert_allclose(out.rot.data[k], one.rot.data, atol=1e-15)


def test_module_and_factor_argument_shapes():
    with pytest.raises(ValueError, match=r"ImuPreintegrator\(gyro_noise\)"):
        ImuPreintegrator(gyro_noise=[1e-3, 2e-3])
    with pytest.raises(ValueError, match=r"ImuPreintegrator\(integration_noise\)"):
        ImuPreintegrator(integration_noise=[1e-3, 2e-3])
    m = ImuPreintegrator(gyro_noise=jnp.float32(1e-3))
    assert m.gyro_noise.shape == (3,) and m.gyro_noise.dtype == jnp.float32
    # a (2, 2) information for a 3-vector residual was accepted
    with pytest.raises(ValueError, match=r"gps_factor\(information\): expected shape \(3, 3\)"):
        gps_factor(np.zeros((2, 3)), [0, 1], information=np.eye(2))
    # a (2, 2) dt was flattened into 4 intervals
    with pytest.raises(ValueError, match=r"bias_walk_factor\(dt\): expected shape \(m,\)"):
        bias_walk_factor([0, 1, 2, 3], [1, 2, 3, 4], np.ones((2, 2)), 1e-3, 1e-3)


def test_float32_samples_with_a_python_scalar_dt_stay_float32():
    """The common call ``preintegrate(gyro32, acc32, 0.005)`` returned float64: the
    scalar's dtype was promoted as a strong float64."""
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    lo = preintegrate(f32(GYRO), f32(ACC), 0.01, gyro_noise=0.1, acc_noise=0.2)
    hi = preintegrate(GYRO, ACC, 0.01, gyro_noise=0.1, acc_noise=0.2)
    for name in ("vel", "pos", "dt", "cov", "jac"):
        assert getattr(lo, name).dtype == jnp.float32, name
        np.testing.assert_allclose(getattr(lo, name), getattr(hi, name), rtol=1e-4,
                                   atol=1e-6, err_msg=name)
    assert lo.rot.data.dtype == jnp.float32


@pytest.mark.parametrize("kw", [{"gyro_noise": -0.01}, {"acc_noise": [0.1, -0.1, 0.1]},
                                {"integration_noise": -1e-3}])
def test_negative_noise_sigma_raises_instead_of_acting_as_its_magnitude(kw):
    # σ is squared: a sign slip (−0.01) silently gave the covariance of +0.01
    from jaxpose.imu import ImuPreintegrator, preintegrate

    g, a = np.zeros((4, 3)), np.tile([0.0, 0.0, 9.81], (4, 1))
    name = next(iter(kw))
    with pytest.raises(ValueError, match=rf"preintegrate\({name}\): expected σ ≥ 0"):
        preintegrate(g, a, 0.01, **kw)
    if name != "integration_noise":
        with pytest.raises(ValueError, match=rf"ImuPreintegrator\({name}\): expected σ ≥ 0"):
            ImuPreintegrator(**kw)
    ok = {"gyro_noise": 0.01, "acc_noise": 0.1, **{k: np.abs(v) for k, v in kw.items()}}
    assert np.isfinite(np.asarray(preintegrate(g, a, 0.01, **ok).cov)).all()
    # a traced σ (learned noise) is checked in the compiled program
    jitted = jax.jit(lambda s: preintegrate(g, a, 0.01, **{**ok, name: s}).cov)
    with pytest.raises(Exception, match=rf"preintegrate\({name}\): expected σ ≥ 0 .*jit"):
        jax.block_until_ready(jitted(jnp.asarray(kw[name])))
    np.testing.assert_allclose(jitted(jnp.asarray(ok[name])),
                               preintegrate(g, a, 0.01, **ok).cov, rtol=1e-12)


def test_navstate_parts_must_share_the_batch_shape():
    # a broadcast velocity was accepted; state[0] then indexed its components and
    # pose() failed inside a concatenate
    from jaxpose.imu import NavState
    from jaxpose.lie import SO3

    rot = SO3.identity((4,))
    with pytest.raises(ValueError, match=r"NavState\(vel\): expected batch shape \(4,\)"):
        NavState(rot, np.zeros(3), np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"NavState\(pos\): expected batch shape \(4,\)"):
        NavState(rot, np.zeros((4, 3)), np.zeros((2, 4, 3)))
    state = NavState(rot, np.zeros((4, 3)), np.ones((4, 3)))
    assert state[1].shape == () and state.pose().data.shape == (4, 7)
    assert jax.vmap(lambda s: s.pos.sum())(state).shape == (4,)


def test_bias_walk_factor_scalar_interval_and_walk_shapes():
    """A scalar dt means one interval for every factor (it raised, blaming ``i``); a σ of
    the wrong shape is named (it was a bare NumPy broadcast error)."""
    from jaxpose.imu import bias_walk_factor

    one = bias_walk_factor([0, 1, 2], [1, 2, 3], 0.1, 1e-3, 2e-3)
    each = bias_walk_factor([0, 1, 2], [1, 2, 3], [0.1, 0.1, 0.1], 1e-3, 2e-3)
    np.testing.assert_array_equal(one.sqrt_info, each.sqrt_info)
    expected = 1.0 / np.sqrt(np.r_[[1e-6] * 3, [4e-6] * 3] * 0.1)  # 1/(σ·√dt), closed form
    np.testing.assert_allclose(np.diagonal(np.asarray(one.sqrt_info)[0]), expected, rtol=1e-12)
    with pytest.raises(ValueError, match=r"bias_walk_factor\(gyro_walk\): expected a scalar or"):
        bias_walk_factor([0, 1], [1, 2], 0.1, [1e-3, 1e-3], 1e-3)
