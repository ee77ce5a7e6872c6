"""Side by side with GTSAM (optional peer, skipped when gtsam is missing), float64.

Same samples, biases and noise settings; the state orderings are mapped explicitly:

* GTSAM's ``preintMeasCov`` is ordered ``[rot, pos, vel]``; jaxpose's ``cov`` is
  ``[δφ, δv, δp]`` (Forster's chart).
* ``PreintegratedImuMeasurementsManifold`` (NavState chart) expresses δp, δv in the frame
  at the window end: ``δv_jaxpose = ΔR·δv_gtsam``.
* ``PreintegratedImuMeasurements`` (tangent scheme, GTSAM's default) keeps ΔR = Exp(θ)
  with additive errors on θ: ``δφ = Jr(θ)·δθ``.
* GTSAM's bias vector is ``[b_a, b_g]``; jaxpose's is ``[b_g, b_a]``.

Acceptance: ΔR, Δv, Δp within 1e-9 and the covariance within 1e-6 relative.
"""

import numpy as np
import pytest

from jaxpose.imu import ImuFactorData, NavState, gps_residual, imu_residual, preintegrate
from jaxpose.lie import SE3, SO3

from . import reference as ref

gtsam = pytest.importorskip("gtsam")
pytestmark = pytest.mark.peer

N = 200
SIGMA_G = np.array([2e-3, 3e-3, 1.5e-3])
SIGMA_A = np.array([3e-2, 2e-2, 4e-2])
SIGMA_I = 1e-3
GRAVITY = 9.81


def _data(seed):
    gyro, acc, dt = ref.random_window(seed, N)
    rng = np.random.default_rng(seed + 100)
    return gyro, acc, dt, rng.normal(size=3) * 0.02, rng.normal(size=3) * 0.1


def _params():
    p = gtsam.PreintegrationParams.MakeSharedU(GRAVITY)
    p.setGyroscopeCovariance(np.diag(SIGMA_G**2))
    p.setAccelerometerCovariance(np.diag(SIGMA_A**2))
    p.setIntegrationCovariance(SIGMA_I**2 * np.eye(3))
    return p


def _gtsam_pim(cls, gyro, acc, dt, bg, ba):
    pim = cls(_params(), gtsam.imuBias.ConstantBias(ba, bg))
    for k in range(len(dt)):
        pim.integrateMeasurement(acc[k], gyro[k], dt[k])
    return pim


PERM = np.zeros((9, 9))  # GTSAM [rot, pos, vel] ← jaxpose [φ, v, p]
PERM[0:3, 0:3] = PERM[3:6, 6:9] = PERM[6:9, 3:6] = np.eye(3)

SCHEMES = {
    "manifold": lambda: gtsam.PreintegratedImuMeasurementsManifold,
    "tangent": lambda: gtsam.PreintegratedImuMeasurements,
}


def _to_gtsam_chart(scheme, pim, R):
    """The linear map from jaxpose's error [δφ, δv, δp] to GTSAM's [rot, pos, vel]."""
    T = np.eye(9)
    if scheme == "manifold":
        T[3:6, 3:6] = T[6:9, 6:9] = R.T  # δ_gtsam = ΔRᵀ·δ_jaxpose (end frame)
    else:
        theta = np.asarray(pim.preintegrated())[0:3]
        T[0:3, 0:3] = np.linalg.inv(ref.right_jacobian(theta))  # δθ = Jr(θ)⁻¹·δφ
    return PERM @ T if scheme == "manifold" else T @ PERM


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_deltas_and_covariance_match_gtsam(scheme):
    seeds = (0, 1)
    data = [_data(s) for s in seeds]
    stack = [np.stack(x) for x in zip(*data, strict=True)]
    out = preintegrate(stack[0], stack[1], stack[2], gyro_bias=stack[3], acc_bias=stack[4],
                       gyro_noise=SIGMA_G, acc_noise=SIGMA_A, integration_noise=SIGMA_I,
                       scheme=scheme)
    for k, (gyro, acc, dt, bg, ba) in enumerate(data):
        pim = _gtsam_pim(SCHEMES[scheme](), gyro, acc, dt, bg, ba)
        R = np.asarray(out.rot.matrix()[k])
        assert abs(float(out.dt[k]) - pim.deltaTij()) < 1e-12
        assert np.abs(R - pim.deltaRij().matrix()).max() < 1e-9
        assert np.abs(np.asarray(out.vel[k]) - pim.deltaVij()).max() < 1e-9
        assert np.abs(np.asarray(out.pos[k]) - pim.deltaPij()).max() < 1e-9
        M = _to_gtsam_chart(scheme, pim, R)
        cov = M @ np.asarray(out.cov[k]) @ M.T
        ref_cov = np.asarray(pim.preintMeasCov())
        rel = np.abs(cov - ref_cov).max() / np.abs(ref_cov).max()
        assert rel < 1e-6, rel
        # and entry by entry, relative to the matching diagonal scale
        scale = np.sqrt(np.outer(np.diag(ref_cov), np.diag(ref_cov)))
        assert np.max(np.abs(cov - ref_cov) / scale) < 1e-6


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_predict_with_bias_correction_matches_gtsam(scheme):
    """``predict`` with gravity, an initial velocity and a bias different from the
    linearisation point: Forster's first-order correction equals GTSAM's manifold scheme
    to rounding; GTSAM's tangent scheme corrects θ additively (a second-order difference)."""
    gyro, acc, dt, bg, ba = _data(3)
    out = preintegrate(gyro, acc, dt, gyro_bias=bg, acc_bias=ba, gyro_noise=SIGMA_G,
                       acc_noise=SIGMA_A, integration_noise=SIGMA_I, scheme=scheme)
    pim = _gtsam_pim(SCHEMES[scheme](), gyro, acc, dt, bg, ba)
    R0 = ref.so3_exp(np.array([0.3, -0.2, 0.5]))
    v0, p0 = np.array([1.0, 2.0, -0.5]), np.array([10.0, -3.0, 2.0])
    state = gtsam.NavState(gtsam.Rot3(R0), p0, v0)
    start = NavState(SO3.from_matrix(R0), v0, p0)
    for db, tol in ((0.0, 1e-9), (1e-3, 1e-9 if scheme == "manifold" else 1e-6)):
        bg1, ba1 = bg + db * np.array([1.0, -0.5, 2.0]), ba + db * np.array([-2.0, 1.0, 0.5])
        expect = pim.predict(state, gtsam.imuBias.ConstantBias(ba1, bg1))
        got = out.predict(start, [0.0, 0.0, -GRAVITY], bg1, ba1)
        assert np.abs(np.asarray(got.rot.matrix()) - expect.attitude().matrix()).max() < tol
        assert np.abs(np.asarray(got.vel) - expect.velocity()).max() < tol * 10
        assert np.abs(np.asarray(got.pos) - expect.position()).max() < tol * 10


def test_gps_residual_matches_gtsam_gpsfactor():
    pose = SE3.random(__import__("jax").random.PRNGKey(3))
    z = np.array([1.0, -2.0, 0.5])
    factor = gtsam.GPSFactor(0, z, gtsam.noiseModel.Isotropic.Sigma(3, 1.0))
    x = pose.data
    gpose = gtsam.Pose3(gtsam.Rot3(np.asarray(SO3(x[3:7]).matrix())), np.asarray(x[:3]))
    np.testing.assert_allclose(gps_residual(pose, z), factor.evaluateError(gpose), atol=1e-14)


def test_imu_factor_cost_matches_gtsam_imufactor_to_first_order():
    """At a state perturbed by ε from the predicted one, jaxpose's whitened IMU cost
    (Forster's residual in the start frame) and GTSAM's ``ImuFactor`` error (residual in
    the end frame, tangent chart) agree to O(ε) relative; at the prediction both vanish."""
    import jax.numpy as jnp

    gyro, acc, dt, bg, ba = _data(4)
    out = preintegrate(gyro, acc, dt, gyro_bias=bg, acc_bias=ba, gyro_noise=SIGMA_G,
                       acc_noise=SIGMA_A, integration_noise=SIGMA_I, scheme="tangent")
    pim = _gtsam_pim(gtsam.PreintegratedImuMeasurements, gyro, acc, dt, bg, ba)
    factor = gtsam.ImuFactor(0, 1, 2, 3, 4, pim)
    R0 = ref.so3_exp(np.array([0.3, -0.2, 0.5]))
    v0, p0 = np.array([1.0, 2.0, -0.5]), np.array([10.0, -3.0, 2.0])
    start = NavState(SO3.from_matrix(R0), v0, p0)
    bg1, ba1 = bg, ba  # (bias correction: test_predict_with_bias_correction_matches_gtsam)
    end = out.predict(start, [0.0, 0.0, -GRAVITY], bg1, ba1)
    data = ImuFactorData(out.rot.data, out.vel, out.pos, out.dt, out.jac,
                         jnp.concatenate([out.gyro_bias, out.acc_bias]),
                         jnp.array([0.0, 0.0, -GRAVITY]))
    info = np.linalg.inv(np.asarray(out.cov))
    rng = np.random.default_rng(0)
    rel = []
    for eps in (0.0, 1e-4, 1e-5):
        d = rng.normal(size=12) * eps * np.array([1.0] * 3 + [1e-1] * 3 + [1.0] * 6)
        rot_j = np.asarray(end.rot.matrix()) @ ref.so3_exp(d[0:3])
        pos_j, vel_j = np.asarray(end.pos) + d[3:6], np.asarray(end.vel) + d[6:9]
        r = imu_residual(start.pose(), jnp.asarray(v0),
                         SE3(jnp.concatenate([pos_j, SO3.from_matrix(rot_j).data])),
                         jnp.asarray(vel_j), jnp.concatenate([bg1, ba1]), data)
        ours = 0.5 * float(r @ info @ r)
        vals = gtsam.Values()
        vals.insert(0, gtsam.Pose3(gtsam.Rot3(R0), p0))
        vals.insert(1, v0)
        vals.insert(2, gtsam.Pose3(gtsam.Rot3(rot_j), pos_j))
        vals.insert(3, vel_j)
        vals.insert(4, gtsam.imuBias.ConstantBias(ba1, bg1))
        theirs = factor.error(vals)
        if eps == 0.0:
            assert ours < 1e-12 and theirs < 1e-12, (ours, theirs)
        else:
            rel.append(abs(ours - theirs) / theirs)
    assert rel[0] < 1e-2 and rel[1] < rel[0] / 5, rel
