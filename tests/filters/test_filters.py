"""EKF / UKF against a closed-form Kalman filter, the particle filter's resampling and
estimates, Lie-group states, and bad input."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.dynamics import LTI, NLS
from jaxpose.filters import (
    EKF,
    UKF,
    ParticleFilter,
    effective_sample_size,
    merwe_weights,
    systematic_resample,
)
from jaxpose.lie import SO2

N_STEPS = 15


def linear_gaussian(dtype=np.float64, seed=0):
    rng = np.random.default_rng(seed)
    n, m, p = 3, 2, 2
    A = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    B, C, D = rng.normal(size=(n, m)), rng.normal(size=(p, n)), rng.normal(size=(p, m))
    c1, c2 = rng.normal(size=n), rng.normal(size=p)
    Q = np.diag(rng.uniform(0.1, 0.5, n))
    R = np.diag(rng.uniform(0.1, 0.5, p)) + 0.05
    x0, P0 = rng.normal(size=n), np.eye(n) + 0.1
    us = rng.normal(size=(N_STEPS, m))
    # data from the model itself
    x, ys = x0 + rng.multivariate_normal(np.zeros(n), P0), []
    for u in us:
        x = A @ x + B @ u + c1 + rng.multivariate_normal(np.zeros(n), Q)
        ys.append(C @ x + D @ u + c2 + rng.multivariate_normal(np.zeros(p), R))
    arrs = dict(A=A, B=B, C=C, D=D, c1=c1, c2=c2, Q=Q, R=R, x0=x0, P0=P0, us=us, ys=np.array(ys))
    return {k: v.astype(dtype) for k, v in arrs.items()}


def kalman_reference(d):
    """Textbook Kalman filter in float64 numpy (predict, then update with y_k)."""
    A, B, C, D, c1, c2, Q, R = (
        np.asarray(d[k], np.float64) for k in ("A", "B", "C", "D", "c1", "c2", "Q", "R")
    )
    x, P = np.asarray(d["x0"], np.float64), np.asarray(d["P0"], np.float64)
    xs, Ps = [], []
    for u, y in zip(np.asarray(d["us"], np.float64), np.asarray(d["ys"], np.float64)):
        x = A @ x + B @ u + c1
        P = A @ P @ A.T + Q
        S = C @ P @ C.T + R
        K = P @ C.T @ np.linalg.inv(S)
        x = x + K @ (y - C @ x - D @ u - c2)
        P = (np.eye(len(x)) - K @ C) @ P
        xs.append(x)
        Ps.append(0.5 * (P + P.T))
    return np.array(xs), np.array(Ps)


def _run(flt, d):
    return eqx.filter_jit(flt.run)(d["x0"], d["P0"], d["ys"], d["us"])


@pytest.mark.parametrize(
    "make",
    [
        lambda s, d: EKF(s, d["Q"], d["R"]),
        lambda s, d: EKF(s, d["Q"], d["R"], joseph=False),
        lambda s, d: UKF(s, d["Q"], d["R"]),
        lambda s, d: UKF(s, d["Q"], d["R"], alpha=0.5, beta=2.0, kappa=1.0),
    ],
    ids=["ekf-joseph", "ekf-simple", "ukf", "ukf-alpha0.5-kappa1"],
)
def test_ekf_ukf_equal_kalman_filter_on_linear_gaussian(make):
    d = linear_gaussian()
    sys = LTI(d["A"], d["B"], d["C"], d["D"], d["c1"], d["c2"])
    res = _run(make(sys, d), d)
    xr, Pr = kalman_reference(d)
    np.testing.assert_allclose(res.x, xr, atol=1e-11, rtol=1e-11)
    np.testing.assert_allclose(res.P, Pr, atol=1e-11, rtol=1e-11)
    assert bool(np.all(res.ok))


def test_filters_float32_path():
    d = linear_gaussian(np.float32)
    sys = LTI(d["A"], d["B"], d["C"], d["D"], d["c1"], d["c2"])
    xr, Pr = kalman_reference(d)
    res = _run(EKF(sys, d["Q"], d["R"]), d)
    assert res.x.dtype == np.float32 and res.P.dtype == np.float32
    np.testing.assert_allclose(res.x, xr, atol=2e-4, rtol=1e-4)
    np.testing.assert_allclose(res.P, Pr, atol=2e-5, rtol=1e-4)


def test_ukf_float32_covariance_with_a_precise_sensor():
    """P0/R = 1e4 on a constant-velocity model: the UKF's P − K·Pyy·Kᵀ (a difference of
    two matrices of P's size) made the float32 covariance 2.1e-3 off the float64 Kalman
    filter's (the Joseph-form EKF: 3e-6); the outer-product form is 1e-5 off."""
    dt = 0.1
    A = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    C = np.array([[1, 0, 0, 0], [0, 1, 0, 0.0]])
    Q, R, P0 = np.diag([1e-6, 1e-6, 1e-4, 1e-4]), 1e-3 * np.eye(2), 10.0 * np.eye(4)
    rng = np.random.default_rng(0)
    x, ys = np.array([1.0, 2.0, 0.5, -0.3]), []
    for _ in range(200):
        x = A @ x + rng.multivariate_normal(np.zeros(4), Q)
        ys.append(C @ x + rng.multivariate_normal(np.zeros(2), R))
    xr, Pr, Ps_ref = np.zeros(4), P0, []
    for y in ys:  # float64 Kalman filter, Joseph form
        xr, Pr = A @ xr, A @ Pr @ A.T + Q
        K = Pr @ C.T @ np.linalg.inv(C @ Pr @ C.T + R)
        xr, I_KC = xr + K @ (y - C @ xr), np.eye(4) - K @ C
        Pr = I_KC @ Pr @ I_KC.T + K @ R @ K.T
        Ps_ref.append(Pr)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    ukf = UKF(LTI(f32(A), f32(np.zeros((4, 1))), f32(C), f32(np.zeros((2, 1)))), f32(Q), f32(R))
    out = eqx.filter_jit(ukf.run)(f32(np.zeros(4)), f32(P0), f32(ys), f32(np.zeros((200, 1))))
    Ps = np.asarray(out.P, np.float64)
    err = np.max(np.abs(Ps - Ps_ref) / np.abs(np.asarray(Ps_ref)).max(axis=(1, 2))[:, None, None])
    assert out.P.dtype == jnp.float32 and err < 1e-4
    assert np.abs(np.asarray(out.x[-1], np.float64) - xr).max() < 2e-5


def test_step_api_matches_runner():
    d = linear_gaussian()
    sys = LTI(d["A"], d["B"], d["C"], d["D"], d["c1"], d["c2"])
    ekf = EKF(sys, d["Q"], d["R"])
    step = eqx.filter_jit(ekf.step)
    x, P = d["x0"], d["P0"]
    for k in range(3):
        x, P = step(x, P, d["ys"][k], d["us"][k])
    xr, Pr = kalman_reference(d)
    np.testing.assert_allclose(x, xr[2], atol=1e-12)
    np.testing.assert_allclose(P, Pr[2], atol=1e-12)


def test_merwe_weights():
    wm, wc, c = merwe_weights(4, 1e-3, 2.0, 0.0, jnp.float64)
    np.testing.assert_allclose(jnp.sum(wm), 1.0, rtol=1e-9)  # α = 1e-3 cancels digits
    lam = 1e-6 * 4 - 4
    np.testing.assert_allclose(wm[0], lam / (4 + lam))
    np.testing.assert_allclose(wc[0], lam / (4 + lam) + 1 - 1e-6 + 2.0)
    np.testing.assert_allclose(c, 4 + lam)
    with pytest.raises(ValueError, match="alpha, kappa"):
        merwe_weights(3, 1.0, 2.0, -3.0, jnp.float64)


# ----------------------------------------------------------------------------------
# Particle filter
# ----------------------------------------------------------------------------------
def test_systematic_resampling_and_ess():
    w = np.array([0.5, 0.25, 0.125, 0.125, 0.0])
    logw = jnp.log(jnp.asarray(w))
    np.testing.assert_allclose(effective_sample_size(logw), 1 / np.sum(w**2))
    idx = jax.jit(systematic_resample)(jax.random.PRNGKey(3), logw)
    counts = np.bincount(np.asarray(idx), minlength=5)
    # systematic resampling: each count is floor or ceil of N·w_i, zero weights never drawn
    assert np.all(counts >= np.floor(5 * w)) and np.all(counts <= np.ceil(5 * w))
    assert counts[4] == 0 and counts.sum() == 5


def test_particle_filter_approaches_kalman_filter():
    d = linear_gaussian()
    sys = LTI(d["A"], d["B"], d["C"], d["D"], d["c1"], d["c2"])
    pf = ParticleFilter(sys, d["Q"], d["R"], num_particles=4000)
    res, ess = eqx.filter_jit(pf.run)(
        jax.random.key(0, impl="rbg"), d["x0"], d["P0"], d["ys"], d["us"]
    )
    xr, Pr = kalman_reference(d)
    err = np.asarray(res.x) - xr
    # Monte-Carlo error of a weighted mean ~ sqrt(P / N_eff)
    scale = np.sqrt(np.einsum("tii->ti", Pr) / 400)
    assert np.all(np.abs(err) < 5 * scale)
    np.testing.assert_allclose(res.P, Pr, rtol=0.3, atol=0.05)
    assert ess.shape == (N_STEPS,) and np.all(ess > 1) and np.all(ess <= 4000)


# ----------------------------------------------------------------------------------
# Lie-group states: a heading on SO(2) equals the same filter written on the angle
# ----------------------------------------------------------------------------------
class HeadingSO2(NLS):
    """X⁺ = X·Exp(ω dt); measures the unit heading vector [cos θ, sin θ]."""

    def state_transition(self, X, u, t=0):
        return X @ SO2.exp(0.1 * u)

    def observation(self, X, u, t=0):
        return X.data


class HeadingAngle(NLS):
    def state_transition(self, x, u, t=0):
        return x + 0.1 * u

    def observation(self, x, u, t=0):
        return jnp.stack([jnp.cos(x[0]), jnp.sin(x[0])])


@pytest.mark.parametrize("Filter", [EKF, UKF])
def test_group_state_filters_match_vector_filter(Filter):
    rng = np.random.default_rng(5)
    us = rng.normal(size=(N_STEPS, 1))
    th = np.cumsum(0.1 * us[:, 0]) + 0.3
    ys = np.stack([np.cos(th), np.sin(th)], -1) + 0.05 * rng.normal(size=(N_STEPS, 2))
    Q, R, P0 = 0.01 * np.eye(1), 0.05**2 * np.eye(2), 0.2 * np.eye(1)
    grp = eqx.filter_jit(Filter(HeadingSO2(), Q, R).run)(SO2.exp(jnp.array([0.0])), P0, ys, us)
    vec = eqx.filter_jit(Filter(HeadingAngle(), Q, R).run)(jnp.array([0.0]), P0, ys, us)
    assert isinstance(grp.x, SO2) and grp.x.shape == (N_STEPS,)
    np.testing.assert_allclose(grp.x.log().data, vec.x, atol=1e-10)
    np.testing.assert_allclose(grp.P, vec.P, atol=1e-12)
    assert abs(float(grp.x[-1].log().data[0]) - th[-1]) < 0.1


# ----------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------
def test_filter_bad_input():
    d = linear_gaussian()
    sys = LTI(d["A"], d["B"], d["C"], d["D"], d["c1"], d["c2"])
    with pytest.raises(ValueError, match="Q: expected a positive semi-definite"):
        EKF(sys, -np.eye(3), d["R"])
    with pytest.raises(ValueError, match="R: expected a positive-definite"):
        UKF(sys, d["Q"], np.zeros((2, 2)))
    with pytest.raises(ValueError, match="R: expected a symmetric"):
        EKF(sys, d["Q"], np.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="R: contains non-finite"):
        ParticleFilter(sys, d["Q"], np.array([[np.nan, 0], [0, 1.0]]))
    with pytest.raises(ValueError, match=r"P0: expected shape \(3, 3\)"):
        EKF(sys, d["Q"], d["R"]).run(d["x0"], np.eye(2), d["ys"], d["us"])
    with pytest.raises(ValueError, match="P0: expected a positive semi-definite"):
        UKF(sys, d["Q"], d["R"]).run(d["x0"], -np.eye(3), d["ys"], d["us"])
    with pytest.raises(ValueError, match=r"us: expected shape \(15, m\)"):
        EKF(sys, d["Q"], d["R"]).run(d["x0"], d["P0"], d["ys"], d["us"][:4])
    with pytest.raises(ValueError, match=r"Q: expected shape \(3, 3\)"):
        EKF(sys, np.eye(2), d["R"]).predict(d["x0"], d["P0"], d["us"][0])
    with pytest.raises(ValueError, match="num_particles: expected an int >= 1"):
        ParticleFilter(sys, d["Q"], d["R"], num_particles=0)
    with pytest.raises(TypeError, match="model: expected a jaxpose.dynamics.System"):
        EKF(lambda x: x, d["Q"], d["R"])
