"""Euler angles at and near gimbal lock against scipy (an independent implementation).

``quaternion_to_euler`` used roll = atan2(R21, R22), yaw = atan2(R10, R00): at pitch = ±π/2
both arguments are zero up to rounding, so the angles did not rebuild the rotation
(|from_euler(euler(R)) − R| up to 0.25). Convention: R = Rz(yaw)·Ry(pitch)·Rx(roll), which
is scipy's extrinsic ``"xyz"`` with angles [roll, pitch, yaw]."""

from __future__ import annotations

import warnings

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from jaxpose.lie import SE3, SO3, convert  # noqa: E402

PITCHES = [np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-9, -(np.pi / 2 - 1e-9), np.pi / 2 - 1e-6,
           -(np.pi / 2 - 1e-4)]


@pytest.mark.parametrize("pitch", PITCHES, ids=lambda p: f"{p:+.12f}")
def test_euler_rebuilds_the_rotation_at_and_near_gimbal_lock(pitch):
    rng = np.random.default_rng(3)
    n = 64
    e = np.stack([rng.uniform(-3, 3, n), np.full(n, pitch), rng.uniform(-3, 3, n)], 1)
    rot = Rotation.from_euler("xyz", e)
    q = rot.as_quat()
    ours = np.asarray(SO3(jnp.asarray(q)).euler())
    # the angles describe the rotation to rounding (scipy's from_euler rebuilds it)
    rebuilt = Rotation.from_euler("xyz", ours).as_matrix()
    np.testing.assert_allclose(rebuilt, rot.as_matrix(), rtol=0, atol=2e-15)
    # ... and so does jaxpose's own from_euler
    np.testing.assert_allclose(np.asarray(SO3.from_euler(jnp.asarray(ours)).matrix()),
                               rot.as_matrix(), rtol=0, atol=2e-15)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Gimbal lock", UserWarning)
        ref = rot.as_euler("xyz")
    np.testing.assert_allclose(ours[:, 1], ref[:, 1], rtol=0, atol=1e-15)  # pitch
    assert np.all(np.abs(ours[:, [0, 2]]) <= np.pi)
    # the same through SE3 and under jit
    se3 = SE3(jnp.asarray(np.concatenate([rng.normal(size=(n, 3)), q], 1)))
    np.testing.assert_allclose(np.asarray(jax.jit(lambda x: x.euler())(se3)), ours,
                               rtol=0, atol=1e-15)


def test_euler_at_exact_lock_sets_yaw_to_zero_like_scipy():
    """Quaternions exactly at the lock (pitch = ±π/2): only roll ∓ yaw is defined; yaw = 0
    and roll equal scipy's ``as_euler`` (which warns and sets the third angle to 0)."""
    s = np.sqrt(0.5)
    qs = [[0.1, 0.7, -0.1, 0.7], [0.2, -0.6, 0.2, 0.6], [0.0, s, 0.0, s], [0.0, -s, 0.0, s],
          [-0.3, 0.6, 0.3, 0.6], [-0.7, 0.1, 0.7, 0.1]]
    q = np.asarray(qs)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    ours = np.asarray(convert.quaternion_to_euler(jnp.asarray(q)))
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Gimbal lock", UserWarning)
        ref = Rotation.from_quat(q).as_euler("xyz")
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(ours[:, 2], 0.0)
    np.testing.assert_allclose(Rotation.from_euler("xyz", ours).as_matrix(),
                               Rotation.from_quat(q).as_matrix(), rtol=0, atol=1e-15)
    # gradients there are finite (not meaningful: the angles are not differentiable)
    jac = jax.jacrev(convert.quaternion_to_euler)(jnp.asarray(q[0]))
    assert np.all(np.isfinite(np.asarray(jac)))


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_euler_at_the_lock_of_a_rotation_built_from_matrices(sign):
    """R = Rz(0.3)·Ry(±π/2)·Rx(0.5) from exact matrices: the pitch is ±π/2 to rounding
    but the quaternion is not exactly at the lock (√(c² + d²) ≈ 1e-16, not 0), and
    euler() returned roll −3.04, yaw 3.04 (pitch +π/2) and roll 0.4, yaw 0.4 (−π/2)
    where the docs promise yaw = 0 as scipy gives (roll 0.2 and 0.8)."""
    def axis(i, t):
        c, s = np.cos(t), np.sin(t)
        m = np.eye(3)
        j, k = [(1, 2), (2, 0), (0, 1)][i]
        m[j, j], m[j, k], m[k, j], m[k, k] = c, -s, s, c
        return m

    lock = np.array([[0.0, 0.0, sign], [0.0, 1.0, 0.0], [-sign, 0.0, 0.0]])
    mat = axis(2, 0.3) @ lock @ axis(0, 0.5)
    ours = np.asarray(SO3.from_matrix(jnp.asarray(mat)).euler())
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Gimbal lock", UserWarning)
        ref = Rotation.from_matrix(mat).as_euler("xyz")
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-15)
    np.testing.assert_allclose(ours, [0.5 - sign * 0.3, sign * np.pi / 2, 0.0], atol=1e-15)
    np.testing.assert_allclose(np.asarray(SO3.from_euler(jnp.asarray(ours)).matrix()), mat,
                               rtol=0, atol=1e-15)


def test_euler_matches_scipy_away_from_the_lock():
    rng = np.random.default_rng(4)
    n = 200
    e = np.stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-1.5, 1.5, n),
                  rng.uniform(-np.pi, np.pi, n)], 1)
    q = Rotation.from_euler("xyz", e).as_quat()
    q = np.where(rng.uniform(size=(n, 1)) < 0.5, -q, q)  # both signs of the quaternion
    ours = np.asarray(convert.quaternion_to_euler(jnp.asarray(q)))
    np.testing.assert_allclose(ours, Rotation.from_quat(q).as_euler("xyz"), rtol=0,
                               atol=1e-14)
    np.testing.assert_allclose(ours, e, rtol=0, atol=1e-14)
    # float32
    ours32 = np.asarray(convert.quaternion_to_euler(jnp.asarray(q, jnp.float32)))
    assert ours32.dtype == np.float32
    np.testing.assert_allclose(ours32, e, rtol=0, atol=2e-6)


@pytest.mark.parametrize("e", [[0.3, 0.4, -0.5], [2.9, -1.2, 3.0], [-0.2, 1.4, 0.1]])
def test_euler_derivatives_match_finite_differences(e):
    """jacfwd and jacrev of the angles in the quaternion agree with central differences of
    scipy's as_euler (no NaN away from the lock)."""
    q0 = Rotation.from_euler("xyz", e).as_quat()
    h = 1e-6
    fd = np.stack([(Rotation.from_quat(q0 + h * dq).as_euler("xyz")
                    - Rotation.from_quat(q0 - h * dq).as_euler("xyz")) / (2 * h)
                   for dq in np.eye(4)], 1)
    # scipy normalises its input: compare along directions tangent to the unit sphere
    proj = np.eye(4) - np.outer(q0, q0)
    for jac in (jax.jacfwd, jax.jacrev):
        ours = np.asarray(jac(convert.quaternion_to_euler)(jnp.asarray(q0)))
        assert np.all(np.isfinite(ours))
        np.testing.assert_allclose(ours @ proj, fd @ proj, rtol=0, atol=1e-8)
    hess = np.asarray(jax.hessian(convert.quaternion_to_euler)(jnp.asarray(q0)))
    assert np.all(np.isfinite(hess))
