"""Bad and extreme input to the filters (issue 19): measurement sizes checked at trace time,
positive semi-definite covariances (UKF sigma points, PF noise), non-finite and absurd
measurements (``skip_nonfinite``; scale-safe PF weights), and a seeded fuzz test of ``run``:
a clear exception or finite outputs / ``ok`` False, never a silent NaN."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxpose.dynamics import LTI, Bicycle
from jaxpose.filters import EKF, UKF, ParticleFilter
from jaxpose.filters._common import psd_cholesky

from .test_filters import kalman_reference, linear_gaussian


def _setup(**over):
    d = linear_gaussian()
    d.update(over)
    return d, LTI(d["A"], d["B"], d["C"], d["D"], d["c1"], d["c2"])


def _pf(sys, d, **kw):
    return ParticleFilter(sys, d["Q"], d["R"], num_particles=64, **kw)


def _run_any(flt, x0, P0, ys, us):
    if isinstance(flt, ParticleFilter):
        return flt.run(jax.random.key(0), x0, P0, ys, us)[0]
    return flt.run(x0, P0, ys, us)


# one compiled runner per filter configuration (arrays, including the filter's, are leaves)
_jit_run = eqx.filter_jit(_run_any)


# ----------------------------------------------------------------------------------
# Sizes: clear errors naming ys / y and R (trace time, so also under jit)
# ----------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["EKF", "UKF", "PF"])
def test_measurement_size_errors_name_ys_and_R(kind):
    d, sys = _setup()
    flt = {"EKF": EKF, "UKF": UKF, "PF": _pf}[kind]
    f = flt(sys, d["Q"], d["R"]) if kind != "PF" else _pf(sys, d)
    bad = np.zeros((15, 3))  # p = 2 measurements, R 2×2
    msg = r"ys: expected shape \(15, 2\) .*R is 2×2\), got shape \(15, 3\)"
    with pytest.raises(ValueError, match=msg):
        _run_any(f, d["x0"], d["P0"], bad, d["us"])
    with pytest.raises(ValueError, match=msg):  # trace time: the same error under jit
        eqx.filter_jit(_run_any)(f, d["x0"], d["P0"], bad, d["us"])
    with pytest.raises(ValueError, match=r"ys: expected shape \(15, 2\).*got shape \(15,\)"):
        _run_any(f, d["x0"], d["P0"], d["ys"][:, 0], d["us"])
    with pytest.raises(ValueError, match="ys: expected a stack of measurements"):
        _run_any(f, d["x0"], d["P0"], np.float64(1.0), d["us"])
    # R of the wrong size for the model's observation
    f3 = (
        (EKF if kind == "EKF" else UKF)(sys, d["Q"], np.eye(3))
        if kind != "PF"
        else (ParticleFilter(sys, d["Q"], np.eye(3), num_particles=8))
    )
    with pytest.raises(ValueError, match=r"R: expected shape \(2, 2\) \(measurement noise: h"):
        _run_any(f3, d["x0"], d["P0"], d["ys"], d["us"])
    # inputs of the wrong width name x0/us (the model's own check names only its u)
    with pytest.raises(ValueError, match=r"x0, us: the model does not accept .*\(3,\)"):
        _run_any(f, d["x0"], d["P0"], d["ys"], np.zeros((15, 3)))
    # single steps name y (and P)
    if kind != "PF":
        with pytest.raises(ValueError, match=r"P: expected shape \(3, 3\) \(state tangent"):
            f.step(d["x0"], np.eye(2), d["ys"][0], d["us"][0])
    if kind == "PF":
        state = f.init(jax.random.key(1), d["x0"], d["P0"])
        with pytest.raises(ValueError, match=r"y: expected shape \(2,\) .*got shape \(3,\)"):
            f.step(jax.random.key(2), state, np.zeros(3), d["us"][0])
    else:
        with pytest.raises(ValueError, match=r"y: expected shape \(2,\) .*got shape \(3,\)"):
            f.step(d["x0"], d["P0"], np.zeros(3), d["us"][0])
        with pytest.raises(ValueError, match=r"y: expected shape \(2,\)"):
            eqx.filter_jit(f.update)(d["x0"], d["P0"], np.zeros(1), d["us"][0])


# ----------------------------------------------------------------------------------
# Positive semi-definite covariances
# ----------------------------------------------------------------------------------
def test_psd_cholesky_against_numpy():
    chol = jax.jit(psd_cholesky)
    rng = np.random.default_rng(0)
    M = rng.normal(size=(5, 5))
    pd = M @ M.T + 0.1 * np.eye(5)
    np.testing.assert_allclose(
        chol(jnp.asarray(pd)), np.linalg.cholesky(pd), rtol=1e-13, atol=1e-13
    )
    for rank in (0, 1, 3):
        V = rng.normal(size=(5, rank))
        A = V @ V.T
        L = np.asarray(chol(jnp.asarray(A)))
        assert np.all(np.isfinite(L)) and np.allclose(L, np.tril(L))
        np.testing.assert_allclose(L @ L.T, A, atol=1e-12)
        assert np.linalg.matrix_rank(L, tol=1e-8) == rank
    big = jnp.asarray(np.diag([1.0] * 20))  # the fori_loop path (k > 16)
    np.testing.assert_allclose(chol(big), np.eye(20), atol=0)
    assert np.isnan(np.asarray(psd_cholesky(jnp.full((2, 2), jnp.nan)))[np.tril_indices(2)]).all()
    # derivatives stay finite at repeated eigenvalues; at a singular matrix √ of a zero
    # pivot has none, and differentiating there raises (it returned 0: silently wrong)
    g = jax.jit(
        jax.grad(
            lambda s: jnp.sum(psd_cholesky(s * jnp.eye(3) + jnp.diag(jnp.array([0.0, 0.0, 1.0]))))
        )
    )
    assert np.isfinite(g(1.0))
    with pytest.raises(Exception, match="covariance that is singular"):
        jax.block_until_ready(g(0.0))


@pytest.mark.parametrize("P0", ["zero", "rank1"])
def test_ukf_with_psd_covariance_equals_kalman_filter(P0):
    """UKF with P0 = 0 (or rank 1) was NaN at every step: on a linear model it must equal
    the closed-form Kalman filter (numpy reference, independent of the code)."""
    v = np.array([1.0, -2.0, 0.5])
    P0m = np.zeros((3, 3)) if P0 == "zero" else np.outer(v, v)
    d, sys = _setup(P0=P0m)
    xr, Pr = kalman_reference(d)
    for flt in (UKF(sys, d["Q"], d["R"]), EKF(sys, d["Q"], d["R"])):
        res = _jit_run(flt, d["x0"], d["P0"], d["ys"], d["us"])
        assert bool(np.all(res.ok))
        np.testing.assert_allclose(res.x, xr, atol=1e-11, rtol=1e-11)
        np.testing.assert_allclose(res.P, Pr, atol=1e-11, rtol=1e-11)


def test_particle_filter_singular_process_noise_spreads_along_its_range():
    """A singular Q used to zero the whole noise factor (NaN Cholesky → 0): now the
    sampled noise has covariance Q, zero only in Q's null direction."""
    Q = np.diag([0.5, 0.0, 0.2])
    d, sys = _setup(Q=Q)
    Lq, _ = _pf(sys, d)._factors()
    np.testing.assert_allclose(Lq @ Lq.T, Q, atol=1e-15)
    st = _pf(sys, d).init(jax.random.key(0), d["x0"], np.diag([1.0, 0.0, 0.0]))
    spread = np.std(np.asarray(st.particles), 0)
    assert spread[0] > 0.5 and spread[1] < 1e-12 and spread[2] < 1e-12


# ----------------------------------------------------------------------------------
# Non-finite and absurd measurements
# ----------------------------------------------------------------------------------
def _skip_reference(d, k):
    """Kalman filter that skips (predicts only) at step k."""
    xr, Pr = kalman_reference({**d, "ys": d["ys"][:k], "us": d["us"][:k]}) if k else ([], [])
    x = xr[-1] if k else d["x0"]
    P = Pr[-1] if k else d["P0"]
    A, B, c1, Q = d["A"], d["B"], d["c1"], d["Q"]
    x, P = A @ x + B @ d["us"][k] + c1, A @ P @ A.T + Q
    rest = {**d, "x0": x, "P0": P, "ys": d["ys"][k + 1 :], "us": d["us"][k + 1 :]}
    xr2, Pr2 = kalman_reference(rest)
    return (
        np.concatenate([np.reshape(xr, (-1, 3)), x[None], xr2]),
        np.concatenate([np.reshape(Pr, (-1, 3, 3)), P[None], Pr2]),
    )


@pytest.mark.parametrize("value", [np.nan, np.inf, 1e200])
def test_skip_nonfinite_predicts_only(value):
    d, sys = _setup()
    k = 4
    ys = d["ys"].copy()
    ys[k, 1] = value
    xr, Pr = _skip_reference(d, k)
    for F in (EKF, UKF):
        res = _jit_run(F(sys, d["Q"], d["R"], skip_nonfinite=True), d["x0"], d["P0"], ys, d["us"])
        ok = np.ones(len(ys), bool)
        ok[k] = False
        np.testing.assert_array_equal(res.ok, ok)
        np.testing.assert_allclose(res.x, xr, atol=1e-10, rtol=1e-10)
        np.testing.assert_allclose(res.P, Pr, atol=1e-10, rtol=1e-10)
        # documented default: the measurement is used; a NaN stays for the rest of the run
        if not np.isfinite(value):
            dflt = _jit_run(F(sys, d["Q"], d["R"]), d["x0"], d["P0"], ys, d["us"])
            np.testing.assert_array_equal(dflt.ok, np.arange(len(ys)) < k)
    res = _jit_run(_pf(sys, d, skip_nonfinite=True), d["x0"], d["P0"], ys, d["us"])
    assert np.all(np.isfinite(res.x)) and np.all(np.isfinite(res.P))
    np.testing.assert_array_equal(res.ok, np.arange(len(ys)) != k)


def test_particle_filter_absurd_measurement_stays_finite():
    """1e200 used to give -inf log-likelihoods for every particle, NaN weights and NaN for
    the rest of the run; now the particles nearest to it take the weight."""
    d, sys = _setup()
    ys = d["ys"].copy()
    ys[4] = 1e200
    res, ess = _pf(sys, d).run(jax.random.key(0), d["x0"], d["P0"], ys, d["us"])
    assert bool(np.all(res.ok)) and np.all(np.isfinite(res.x)) and np.all(np.isfinite(ess))
    # the particles tied (in floating point) for nearest keep the weight, the rest get none
    assert 1.0 <= float(ess[4]) < 64.0
    xr, _ = kalman_reference(d)  # and the filter is back on track afterwards
    assert np.max(np.abs(np.asarray(res.x[-1]) - xr[-1])) < 1.5


def test_skip_nonfinite_gradient_is_finite():
    d, sys = _setup()
    ys = d["ys"].copy()
    ys[3] = np.nan
    ekf = EKF(sys, d["Q"], d["R"], skip_nonfinite=True)
    g = jax.grad(lambda x0: jnp.sum(ekf.run(x0, d["P0"], ys, d["us"]).x[-1]))(d["x0"])
    assert np.all(np.isfinite(g))


# ----------------------------------------------------------------------------------
# Fuzz: malformed / extreme inputs to run
# ----------------------------------------------------------------------------------
_N = 6
_VALUES = st.sampled_from([np.nan, np.inf, -np.inf, 1e200, -1e200, 1e-300, 0.0, 1e8])


@settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    kind=st.sampled_from(["EKF", "UKF", "PF"]),
    skip=st.booleans(),
    p=st.sampled_from([2, 2, 2, 3, 1]),
    n_us=st.sampled_from([_N, _N, _N, _N - 1]),
    P0=st.sampled_from(["eye", "zero", "rank1", "huge"]),
    hits=st.lists(st.tuples(st.integers(0, _N - 1), st.integers(0, 1), _VALUES), max_size=3),
)
def test_fuzz_filter_run(kind, skip, p, n_us, P0, hits):
    rng = np.random.default_rng(0)
    sys = LTI(
        np.eye(2) + 0.1 * rng.normal(size=(2, 2)), rng.normal(size=(2, 1)), rng.normal(size=(2, 2))
    )
    Q, R = 0.1 * np.eye(2), 0.2 * np.eye(2)
    P0m = {
        "eye": np.eye(2),
        "zero": np.zeros((2, 2)),
        "rank1": np.ones((2, 2)),
        "huge": 1e150 * np.eye(2),
    }[P0]
    ys = rng.normal(size=(_N, p))
    for i, j, v in hits:
        ys[i, min(j, p - 1)] = v
    us = rng.normal(size=(n_us, 1))
    if kind == "PF":
        flt = ParticleFilter(sys, Q, R, num_particles=16, skip_nonfinite=skip)
    else:
        flt = (EKF if kind == "EKF" else UKF)(sys, Q, R, skip_nonfinite=skip)
    if p != 2 or n_us != _N:
        with pytest.raises(ValueError, match="ys: expected|us: expected"):
            _run_any(flt, np.zeros(2), P0m, ys, us)
        return
    res = _jit_run(flt, np.zeros(2), P0m, ys, us)
    ok = np.asarray(res.ok)
    finite = np.isfinite(np.asarray(res.x)).all(1) & np.isfinite(np.asarray(res.P)).all((1, 2))
    assert np.all(finite[ok]), "a non-finite estimate flagged ok"  # never a silent NaN
    bad_rows = [i for i, _, v in hits if not np.isfinite(v)]
    if skip:
        assert np.all(finite), "skip_nonfinite must keep every estimate finite"
        assert not np.any(ok[bad_rows])


def test_tangent_space_of_lie_elements_under_jit():
    """Lie elements define __array__ (np.asarray(X) is X.data) yet are pytree states: the
    tangent space of a group or algebra state must not go through np.asarray (it fails on
    tracers)."""
    import equinox as eqx
    import jax.numpy as jnp

    import jaxpose as jp
    from jaxpose.dynamics._tangent import tangent_space

    dim = eqx.filter_jit(lambda a, g: (tangent_space(a).dim, tangent_space(g).dim))
    assert dim(jp.so3(jnp.zeros(3)), jp.SE2.identity()) == (3, 3)


def test_ekf_step_on_a_bicycle_landmark_matches_numpy():
    """At rest on landmark 0 (x0 = 0, the default origin) the range Jacobian was NaN and
    the EKF step all NaN. Reference: the textbook Kalman step in numpy with F = I + dt·e₀e₃ᵀ
    (the RK4 step of the linearisation ṗx = v, exact since it is nilpotent) and H of
    rows d/|d| (0 on the landmark: the subgradient) and e₃ (speed)."""
    model, dt = Bicycle(dt=0.1), 0.1
    Q, R, P = np.eye(4) * 1e-3, np.eye(5) * 0.1, np.eye(4) * 0.1
    x0, u = np.zeros(4), np.zeros(2)
    L = np.asarray(model.landmarks)
    h0 = np.r_[np.hypot(L[:, 0], L[:, 1]), 0.0]
    y = h0 + 0.01
    F = np.eye(4)
    F[0, 3] = dt
    H = np.zeros((5, 4))
    H[1:4, :2] = -L[1:] / h0[1:4, None]
    H[4, 3] = 1.0
    Pp = F @ P @ F.T + Q
    S = H @ Pp @ H.T + R
    K = Pp @ H.T @ np.linalg.inv(S)
    x_ref = K @ (y - h0)
    IKH = np.eye(4) - K @ H
    P_ref = IKH @ Pp @ IKH.T + K @ R @ K.T
    x1, P1 = EKF(model, Q, R).step(x0, P, y, u)
    np.testing.assert_allclose(x1, x_ref, atol=1e-14)
    np.testing.assert_allclose(P1, P_ref, atol=1e-14)
    res = EKF(model, Q, R).run(x0, P, np.tile(y, (3, 1)), np.zeros((3, 2)))
    assert bool(np.all(res.ok)) and np.all(np.isfinite(res.P))


@pytest.mark.parametrize("Filter", [EKF, UKF])
def test_single_step_methods_check_P_like_run(Filter):
    """step/predict/update never checked P (only run's P0): UKF.step(P = −I) returned the
    numbers of P = 0 (the semidefinite Cholesky zeroes negative directions), EKF.step NaN.
    As for P0: values checked eagerly, the shape also under jit."""
    d, sys = _setup()
    flt = Filter(sys, d["Q"], d["R"])
    x, y, u = d["x0"], d["ys"][0], d["us"][0]
    calls = {
        "step": lambda P: flt.step(x, P, y, u),
        "predict": lambda P: flt.predict(x, P, u),
        "update": lambda P: flt.update(x, P, y, u),
    }
    asym = np.eye(3) + np.triu(np.ones((3, 3)), 1)
    for name, call in calls.items():
        with pytest.raises(ValueError, match="P: expected a positive semi-definite"):
            call(-np.eye(3))
        with pytest.raises(ValueError, match="P: expected a symmetric matrix"):
            call(asym)
        with pytest.raises(ValueError, match=r"P: expected shape \(3, 3\)"):
            jax.jit(call)(np.eye(2))
    # a valid P: one step equals the numpy Kalman filter's first step
    xr, Pr = kalman_reference(d)
    x1, P1 = flt.step(x, d["P0"], y, u)
    np.testing.assert_allclose(x1, xr[0], atol=1e-12)
    np.testing.assert_allclose(P1, Pr[0], atol=1e-12)


def test_integer_state_and_empty_sequence_errors():
    """An integer x0 reached jacfwd ("requires real-valued inputs"): it is promoted like
    every array argument. N = 0 measurements gave a bare IndexError."""
    d, sys = _setup()
    d["x0"] = np.array([1, -2, 0])
    xr, Pr = kalman_reference(d)
    for flt in (EKF(sys, d["Q"], d["R"]), UKF(sys, d["Q"], d["R"])):
        x1, P1 = flt.step(d["x0"], d["P0"], d["ys"][0], d["us"][0])
        np.testing.assert_allclose(x1, xr[0], atol=1e-12)
        res = flt.run(d["x0"], d["P0"], d["ys"][:2], d["us"][:2])
        np.testing.assert_allclose(res.x, xr[:2], atol=1e-12)
        np.testing.assert_allclose(res.P, Pr[:2], atol=1e-12)
    for flt in (EKF(sys, d["Q"], d["R"]), UKF(sys, d["Q"], d["R"]), _pf(sys, d)):
        with pytest.raises(ValueError, match="ys: expected at least one measurement"):
            _run_any(flt, d["x0"], d["P0"], d["ys"][:0], d["us"][:0])


@pytest.mark.parametrize("Filter", [EKF, UKF])
def test_bicycle_filters_stay_in_float32(Filter):
    # the model's float64 default landmarks promoted a float32 state (x64 on): run() failed
    # with a scan carry-dtype error and step() returned float64
    f32 = jnp.float32
    filt = Filter(Bicycle(dt=0.1), Q=jnp.eye(4, dtype=f32) * 1e-3, R=jnp.eye(5, dtype=f32) * 0.1)
    x0, P0 = jnp.array([3.0, 4.0, 0.3, 1.0], f32), jnp.eye(4, dtype=f32) * 0.1
    out = filt.run(x0, P0, jnp.ones((5, 5), f32), jnp.zeros((5, 2), f32))
    assert out.x.dtype == f32 and bool(jnp.all(jnp.isfinite(out.x)))
    x, P = filt.step(x0, P0, jnp.ones(5, f32), jnp.zeros(2, f32))
    assert x.dtype == f32 and P.dtype == f32


def test_ukf_derivative_at_a_singular_covariance_raises():
    # psd_cholesky's zero columns gave d/ds of the UKF at P = s·I, s = 0, as 0 where the
    # true (one-sided) derivative is 1; at s > 0 it matches central differences
    model = LTI(jnp.array([[1.0, 0.1], [0.0, 1.0]]), jnp.array([[0.0], [0.1]]),
                jnp.eye(2), jnp.zeros((2, 1)))
    ukf = UKF(model, Q=jnp.eye(2) * 1e-2, R=jnp.eye(2) * 1e-1)

    def p00(s):
        return ukf.predict(jnp.zeros(2), s * jnp.eye(2), jnp.zeros(1))[1][0, 0]

    with pytest.raises(Exception, match="differentiating through a covariance that is "
                                        "singular"):
        jax.grad(p00)(0.0)
    s, h = 0.3, 1e-6
    np.testing.assert_allclose(float(jax.grad(p00)(s)),
                               (float(p00(s + h)) - float(p00(s - h))) / (2 * h), rtol=1e-6)
    assert np.isfinite(float(p00(0.0)))  # values at P = 0 stay available


@pytest.mark.parametrize("kind", ["EKF", "UKF", "PF"])
def test_noise_and_start_covariances_are_checked_under_jit(kind):
    """Q, R and P0 computed inside a jitted function (e.g. learned) skipped the value
    checks: a negative-definite R ran through (NaN or skipped updates) and a P0 with a
    negative eigenvalue gave numbers. They now raise in the compiled program too."""
    jax.config.update("jax_enable_x64", True)
    d, sys = _setup()
    Filter = {"EKF": EKF, "UKF": UKF, "PF": None}[kind]

    def run(Q, R, P0):
        flt = _pf(sys, dict(d, Q=Q, R=R)) if kind == "PF" else Filter(sys, Q, R)
        return _run_any(flt, d["x0"], P0, d["ys"], d["us"]).x

    jitted = jax.jit(run)
    good = (d["Q"], d["R"], d["P0"])
    ref = run(*good)
    np.testing.assert_allclose(jitted(*good), ref, rtol=1e-9, atol=1e-12)
    cases = {
        "R": (0, -np.asarray(d["R"]), "positive-definite"),
        "Q": (1, -np.eye(3) * 0.1, "positive semi-definite"),
        "P0": (2, np.diag([1.0, -1.0, 1.0]), "positive semi-definite"),
    }
    for name, (_, bad, kind_text) in cases.items():
        args = dict(Q=d["Q"], R=d["R"], P0=d["P0"])
        args[name] = bad
        with pytest.raises(ValueError, match=rf"{name}: expected a positive"):
            run(**args)  # eagerly: the existing check, with the eigenvalue
        with pytest.raises(Exception, match=rf"{name}: expected a finite, symmetric, "
                                            rf"{kind_text} matrix \(checked under jit\)"):
            jax.block_until_ready(jitted(**args))
    asym = np.asarray(d["Q"]) + np.triu(np.full((3, 3), 0.01), 1)
    with pytest.raises(Exception, match=r"Q: expected a finite, symmetric"):
        jax.block_until_ready(jitted(asym, d["R"], d["P0"]))
    # differentiating a jitted run through a learned, valid Q still works
    g = jax.grad(lambda s: jnp.sum(jitted(s * jnp.asarray(d["Q"]), d["R"], d["P0"])))(1.0)
    assert np.isfinite(float(g))


@pytest.mark.parametrize("skip", [False, True])
def test_particle_filter_one_nan_particle_observation_loses_only_that_particle(skip):
    """h(x) = √x with one of 1000 particles negative: its NaN observation made every
    log-likelihood NaN (max |z| and min ‖z‖² propagate NaN), so mean, covariance and ESS
    were NaN for the rest of the run (skip_nonfinite: the measurement was skipped and the
    999 good particles never reweighted). Reference: the same run with that particle's
    observation replaced by a huge finite value (it then loses its weight the same way)."""
    from jaxpose.dynamics import System

    class Sqrt(System):
        def state_transition(self, x, u, t=0):
            return x

        def observation(self, x, u, t=0):
            return jnp.sqrt(x)

    class Far(Sqrt):
        def observation(self, x, u, t=0):
            return jnp.where(x >= 0, jnp.sqrt(jnp.abs(x)), 1e6)

    ys, us = jnp.full((3, 1), np.sqrt(3.0)), jnp.zeros((3, 1))
    noise = 0.01 * jnp.eye(1)
    run = [ParticleFilter(m(), noise, noise, num_particles=1000, skip_nonfinite=skip).run(
        jax.random.PRNGKey(0), jnp.array([3.0]), jnp.eye(1), ys, us) for m in (Sqrt, Far)]
    (got, got_ess), (want, want_ess) = run
    np.testing.assert_array_equal(np.asarray(got.ok), True)
    np.testing.assert_allclose(got.x, want.x, rtol=1e-12)
    np.testing.assert_allclose(got_ess, want_ess, rtol=1e-12)
    assert abs(float(got.x[-1, 0]) - 3.0) < 0.05


@pytest.mark.parametrize("filt", ["ekf", "ukf", "pf"])
def test_noise_put_in_after_construction_is_checked(filt):
    """EKF(R=−0.5·I) is refused when made, but the same R put in with eqx.tree_at gave a
    step with a negative posterior variance (−0.67) and a run with NaN covariances; a
    negative Q a zero covariance. step and run check Q and R where known, and run also
    under jit (the filter traced)."""
    sys = LTI(np.eye(2), np.eye(2))
    make = {"ekf": EKF, "ukf": UKF,
            "pf": lambda *a: ParticleFilter(*a, num_particles=16)}[filt]
    good = make(sys, np.eye(2), np.eye(2))
    x0, P0, ys, us = jnp.zeros(2), jnp.eye(2), jnp.ones((3, 2)), jnp.zeros((3, 2))
    for field, value, match in (
            ("R", -0.5 * jnp.eye(2), r"R: expected a (finite, symmetric, )?positive-definite"),
            ("Q", -jnp.eye(2), r"Q: expected a (finite, symmetric, )?positive semi-definite")):
        bad = eqx.tree_at(lambda f, field=field: getattr(f, field), good, value)
        with pytest.raises(ValueError, match=match):
            _run_any(bad, x0, P0, ys, us)
        if filt != "pf":
            with pytest.raises(ValueError, match=match):
                bad.step(x0, P0, ys[0], us[0])
        with pytest.raises(Exception, match=match):  # traced: checked in the program
            jax.block_until_ready(jax.jit(lambda f: _run_any(f, x0, P0, ys, us))(bad))
