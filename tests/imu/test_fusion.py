"""IMU / GPS / prior factors (analytic Jacobians vs autodiff, zero residual at the
prediction) and IMU+GPS fusion on GTSAM's example stream (``../shared/data/imu``): the
reader, dead reckoning against the GPS fixes, and the fused estimate with simulated IMU
biases and noise (skipped when the data set is absent)."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.imu import (
    NavState,
    dead_reckon,
    fuse_imu_gps,
    imu_residual,
    preintegrate,
    preintegrate_windows,
    read_imu_gps,
)
from jaxpose.imu._factors import (
    ImuFactorData,
    gps_jacobian,
    gps_residual,
    imu_jacobian,
    pose_prior_jacobian,
    pose_prior_residual,
)
from jaxpose.lie import SE3, SO3

from . import reference as ref

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "imu" / "imuAndGPSdata.csv"
GRAVITY = jnp.array([0.0, 0.0, -9.81])


def _factor_data(seed=0):
    gyro, acc, dt = ref.random_window(seed, 40)
    rng = np.random.default_rng(seed)
    pre = preintegrate(gyro, acc, dt, gyro_bias=rng.normal(size=3) * 0.01,
                       acc_bias=rng.normal(size=3) * 0.1, gyro_noise=1e-3, acc_noise=1e-2)
    data = ImuFactorData(pre.rot.data, pre.vel, pre.pos, pre.dt, pre.jac,
                         jnp.concatenate([pre.gyro_bias, pre.acc_bias]), GRAVITY)
    return pre, data


@jax.jit
def _jacobians(xi, vi, xj, vj, b, data, z):
    def res(d):
        return imu_residual(xi.retract(d[0:6]), vi + d[6:9], xj.retract(d[9:15]),
                            vj + d[15:18], b + d[18:24], data)

    auto_imu = jax.jacfwd(res)(jnp.zeros(24))
    auto_gps = jax.jacfwd(lambda d: gps_residual(xi.retract(d), z))(jnp.zeros(6))
    auto_prior = jax.jacfwd(lambda d: pose_prior_residual(xi.retract(d), xj))(jnp.zeros(6))
    r, *blocks = imu_jacobian(xi, vi, xj, vj, b, data)
    return (auto_imu, jnp.concatenate(blocks, -1), res(jnp.zeros(24)) - r,
            auto_gps, gps_jacobian(xi, z)[1], auto_prior, pose_prior_jacobian(xi, xj)[1])


def test_analytic_factor_jacobians_equal_autodiff():
    _, data = _factor_data()
    xi, xj = SE3.random(jax.random.PRNGKey(0)), SE3.random(jax.random.PRNGKey(1))
    rng = np.random.default_rng(1)
    vi, vj = jnp.asarray(rng.normal(size=3)), jnp.asarray(rng.normal(size=3))
    b = jnp.asarray(rng.normal(size=6) * 0.05)  # away from the linearisation point
    out = _jacobians(xi, vi, xj, vj, b, data, jnp.array([1.0, 2.0, 3.0]))
    auto, analytic, dr, auto_gps, gps, auto_prior, prior = out
    np.testing.assert_allclose(analytic, auto, atol=1e-12 * float(jnp.abs(auto).max()))
    np.testing.assert_allclose(dr, 0.0, atol=1e-15)
    np.testing.assert_allclose(gps, auto_gps, atol=1e-14)
    np.testing.assert_allclose(prior, auto_prior, atol=1e-13)


def test_imu_residual_vanishes_at_the_bias_corrected_prediction():
    pre, data = _factor_data(2)
    start = NavState(SO3.from_matrix(ref.so3_exp(np.array([0.1, 0.5, -0.2]))),
                     np.array([1.0, 0.0, 2.0]), np.array([5.0, 1.0, -1.0]))
    bg, ba = pre.gyro_bias + 0.003, pre.acc_bias - 0.02
    end = pre.predict(start, GRAVITY, bg, ba)
    r = imu_residual(start.pose(), start.vel, end.pose(), end.vel,
                     jnp.concatenate([bg, ba]), data)
    np.testing.assert_allclose(r, 0.0, atol=1e-12)


# ----------------------------------------------------------------------------------
# GTSAM's IMU + GPS stream
# ----------------------------------------------------------------------------------
needs_data = pytest.mark.skipif(not DATA.is_file(), reason=f"{DATA} not present")


@pytest.fixture(scope="module")
def stream():
    return read_imu_gps(DATA)


@needs_data
def test_reader_and_gps_fixes_equal_dead_reckoning_from_rest(stream):
    """20000 IMU rows, 100 fixes (one after the first sample, then every 200); the initial
    row reads as [p, v, q] (see jaxpose.imu._data); dead reckoning from rest with
    dt = 0.005 s and zero gravity reproduces every fix to its printed precision."""
    d = stream
    assert d.acc.shape == (20000, 3) and d.gps_position.shape == (100, 3)
    assert d.initial_layout == "p,v,q"
    np.testing.assert_array_equal(d.gps_index[:3], [1, 201, 401])
    np.testing.assert_array_equal(d.init_rotation, [0, 0, 0, 1])
    init = NavState(SO3(jnp.asarray(d.init_rotation)), d.init_velocity, d.init_position)
    states = jax.jit(dead_reckon)(d.gyro, d.acc, 0.005, jnp.zeros(3), init)
    pos = np.asarray(states.pos)[d.gps_index - 1]
    np.testing.assert_allclose(pos, d.gps_position, atol=1e-6, rtol=1e-9)


SMOKE_FIXES = 11  # keyframes at the start and at 11 fixes: 2201 samples, 11 windows


def _corrupt(d, n, seed=0):
    """The first ``n`` samples with constant biases, white noise at GTSAM's example
    densities, and 0.5-m GPS noise."""
    rng = np.random.default_rng(seed)
    bg, ba = np.array([2e-4, -1e-4, 3e-4]), np.array([0.02, -0.01, 0.015])
    gyro = d.gyro[:n] + bg + rng.normal(size=(n, 3)) * 2.05689024915e-4 / np.sqrt(0.005)
    acc = d.acc[:n] + ba + rng.normal(size=(n, 3)) * 3.924e-4 / np.sqrt(0.005)
    z = d.gps_position + rng.normal(size=d.gps_position.shape) * 0.5
    return gyro, acc, z, bg, ba


@needs_data
def test_fusion_corrects_dead_reckoning_drift(stream):
    d = stream
    k = SMOKE_FIXES
    n = int(d.gps_index[k - 1])
    init = NavState(SO3(jnp.asarray(d.init_rotation)), d.init_velocity, d.init_position)
    truth = d.gps_position[:k]
    # clean stream: dead reckoning and the fusion both reproduce the fixes
    clean = fuse_imu_gps(d.gyro[:n], d.acc[:n], 0.005, d.gps_index[:k], truth, init)
    assert clean.solution.status_name == "converged"
    kf = np.searchsorted(clean.keyframes, d.gps_index[:k])
    np.testing.assert_allclose(np.asarray(clean.pose.data[kf, :3]), truth, atol=1e-4)
    # corrupted stream (same graph structure: the compiled solver is reused)
    gyro, acc, z, bg, ba = _corrupt(d, n)
    res = fuse_imu_gps(gyro, acc, 0.005, d.gps_index[:k], z[:k], init, gps_sigma=0.5)
    assert res.solution.status_name == "converged"
    fused = np.linalg.norm(np.asarray(res.pose.data[kf, :3]) - truth, axis=1)
    drift = np.linalg.norm(np.asarray(res.dead_reckoning.pos[kf]) - truth, axis=1)
    assert drift[-1] > 0.5  # ½·b_a·t² ≈ 0.9 m after 11 s
    assert np.sqrt(np.mean(fused**2)) < 0.35 and fused[-1] < drift[-1] / 2, (fused, drift)
    # the accelerometer bias along the motion (x) moves from its zero prior towards the
    # truth (0.02; the prior σ 1e-3 and the random walk hold it back over 11 s)
    assert 0.002 < float(res.bias[-1, 3]) < 0.04
    # rotation stays close to the ground-truth orientations (identity)
    rot_err = np.linalg.norm(np.asarray(SO3(res.pose.data[kf, 3:7]).log().data), axis=1)
    assert rot_err.max() < 0.01


def test_preintegrate_windows_equals_separate_calls():
    gyro, acc, dt = ref.random_window(3, 50)
    bounds = [0, 20, 40, 50]  # two windows of 20 samples (one batched call), one of 10
    kw = dict(gyro_noise=1e-3, acc_noise=1e-2)
    pre = preintegrate_windows(gyro, acc, dt, bounds, **kw)
    assert pre.vel.shape == (3, 3)
    first = preintegrate(gyro[:40].reshape(2, 20, 3), acc[:40].reshape(2, 20, 3),
                         dt[:40].reshape(2, 20), **kw)
    last = preintegrate(gyro[None, 40:], acc[None, 40:], dt[None, 40:], **kw)
    for w, (one, k) in enumerate(((first, 0), (first, 1), (last, 0))):
        np.testing.assert_allclose(pre.pos[w], one.pos[k], atol=1e-15)
        np.testing.assert_allclose(pre.cov[w], one.cov[k], rtol=1e-12, atol=1e-20)
        np.testing.assert_allclose(pre.jac[w], one.jac[k], rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match="increasing sample indices"):
        preintegrate_windows(gyro, acc, dt, [0, 30, 20])


@needs_data
@pytest.mark.slow
def test_fusion_full_stream(stream):
    """All 100 fixes (100 s): dead reckoning drifts by over 100 m (½·b_a·t²), the fused
    positions stay at the GPS noise level; pitch and yaw errors are at most half the dead
    reckoning's, and roll (about the direction of travel, unobservable on this stream)
    only follows the gyro-bias drift."""
    d = stream
    n = int(d.gps_index[-1])
    init = NavState(SO3(jnp.asarray(d.init_rotation)), d.init_velocity, d.init_position)
    gyro, acc, z, bg, ba = _corrupt(d, n)
    res = fuse_imu_gps(gyro, acc, 0.005, d.gps_index, z, init, gps_sigma=0.5)
    assert res.solution.status_name == "converged"
    kf = np.searchsorted(res.keyframes, d.gps_index)
    truth = d.gps_position
    fused = np.linalg.norm(np.asarray(res.pose.data[kf, :3]) - truth, axis=1)
    drift = np.linalg.norm(np.asarray(res.dead_reckoning.pos[kf]) - truth, axis=1)
    assert drift[-1] > 100.0 and np.sqrt(np.mean(fused**2)) < 0.4 and fused.max() < 1.0
    rot = np.abs(np.asarray(SO3(res.pose.data[kf, 3:7]).log().data)).max(0)
    dr_rot = np.abs(np.asarray(res.dead_reckoning.rot.log().data[kf])).max(0)
    assert np.all(rot[1:] < 0.5 * dr_rot[1:]), (rot, dr_rot)
    assert rot[0] < 1.5 * abs(bg[0]) * 100  # roll: the bias drift only


@pytest.mark.slow  # ~12 s: two more fusion compilations (float64 and float32)
@needs_data
def test_fusion_float32_stream_with_x64_on(stream):
    """A float32 noisy stream and initial state with x64 on: the GPS positions were cast
    to float64 inside, the residuals came out float64 against float32 variables, and the
    solve failed with a while_loop carry TypeError. It now runs in float32 and agrees
    with the float64 fusion to float32 accuracy (2.4e-7 m here)."""
    d, k, f32 = stream, 4, np.float32
    n = int(d.gps_index[k - 1])
    gyro, acc, z, _, _ = _corrupt(d, n)
    init64 = NavState(SO3(jnp.asarray(d.init_rotation)), d.init_velocity, d.init_position)
    init32 = jax.tree.map(lambda x: jnp.asarray(x, f32), init64)
    want = fuse_imu_gps(gyro, acc, 0.005, d.gps_index[:k], z[:k], init64, gps_sigma=0.5)
    got = fuse_imu_gps(gyro.astype(f32), acc.astype(f32), 0.005, d.gps_index[:k],
                       z[:k].astype(f32), init32, gps_sigma=0.5)
    assert got.solution.status_name == "converged" and got.pose.data.dtype == f32
    np.testing.assert_allclose(got.pose.data[:, :3], want.pose.data[:, :3], atol=1e-5)
