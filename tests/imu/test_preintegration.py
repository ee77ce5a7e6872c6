"""Preintegration values, covariance and bias Jacobians against Forster et al.'s sequential
recurrences (independent numpy reference), closed forms (constant rotation rate, constant
acceleration, an IMU at rest under gravity), composition, first-order bias correction and
dead reckoning. Float64.

Compilation dominates: every call below goes through :func:`preintegrate`'s compiled core
with the same argument structure (biases and noise always given, batch 3 × 40 samples), so
the tests share a handful of compilations."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxpose.imu import ImuPreintegrator, NavState, Preintegrated, dead_reckon, preintegrate
from jaxpose.lie import SO3

from . import reference as ref

B, N = 3, 40
SIGMA_G = np.array([2e-3, 3e-3, 1.5e-3])
SIGMA_A = np.array([3e-2, 2e-2, 4e-2])
SIGMA_I = 1e-3
ZERO = np.zeros((B, 3))


def run(g, a, d, bg=ZERO, ba=ZERO, sg=SIGMA_G, sa=SIGMA_A, si=SIGMA_I, **kw):
    return preintegrate(g, a, d, gyro_bias=bg, acc_bias=ba, gyro_noise=sg, acc_noise=sa,
                        integration_noise=si, **kw)


def _batch(seeds=(0, 1, 2), n=N):
    gs, as_, ds = zip(*(ref.random_window(s, n) for s in seeds), strict=True)
    rng = np.random.default_rng(99)
    bg = rng.normal(size=(len(seeds), 3)) * 0.02
    ba = rng.normal(size=(len(seeds), 3)) * 0.1
    return np.stack(gs), np.stack(as_), np.stack(ds), bg, ba


BATCH = _batch()
REFS = [ref.preintegrate(*(x[k] for x in BATCH), SIGMA_G, SIGMA_A, SIGMA_I) for k in range(B)]


def _assert_close(out, k, expect, idx=(), atol_cov=1e-13):
    R, v, p, cov, jac = expect
    at = lambda x: np.asarray(x)[(k, *idx)]  # noqa: E731
    np.testing.assert_allclose(at(out.rot.matrix()), R, atol=1e-13)
    np.testing.assert_allclose(at(out.vel), v, atol=1e-13)
    np.testing.assert_allclose(at(out.pos), p, atol=1e-13)
    np.testing.assert_allclose(at(out.cov), cov, rtol=1e-9, atol=atol_cov * np.abs(cov).max())
    np.testing.assert_allclose(at(out.jac), jac, rtol=1e-10, atol=1e-13)


def test_window_matches_forster_recurrences():
    g, a, d, bg, ba = BATCH
    out = run(g, a, d, bg, ba)
    assert out.vel.shape == (B, 3) and out.cov.shape == (B, 9, 9) and out.jac.shape == (B, 9, 6)
    np.testing.assert_allclose(out.dt, d.sum(-1), rtol=1e-14)
    for k in range(B):
        _assert_close(out, k, REFS[k])
    np.testing.assert_allclose(out.cov, np.swapaxes(out.cov, -1, -2), atol=1e-20)
    assert np.all(np.linalg.eigvalsh(out.cov) > 0)
    np.testing.assert_allclose(out.gyro_bias, bg)
    # bias-Jacobian accessors are blocks of jac
    np.testing.assert_array_equal(out.d_vel_d_acc_bias, out.jac[:, 3:6, 3:6])
    np.testing.assert_array_equal(out.d_rot_d_gyro_bias, out.jac[:, 0:3, 0:3])


def test_prefix_matches_recurrences_at_every_sample():
    g, a, d, bg, ba = BATCH
    out = run(g, a, d, bg, ba, prefix=True)
    assert out.vel.shape == (B, N, 3) and out.cov.shape == (B, N, 9, 9)
    for n in (1, 7, N):
        expect = ref.preintegrate(g[1, :n], a[1, :n], d[1, :n], bg[1], ba[1],
                                  SIGMA_G, SIGMA_A, SIGMA_I)
        _assert_close(out, 1, expect, idx=(n - 1,))
    np.testing.assert_allclose(out.dt[1], np.cumsum(d[1]), rtol=1e-14)


def test_tangent_scheme_agrees_to_first_order():
    """GTSAM's tangent scheme differs from the exact manifold one by O(dt²) per sample
    (exact agreement with GTSAM: ``test_gtsam.py``)."""
    g, a, d, bg, ba = BATCH
    out = run(g, a, d, bg, ba, scheme="tangent")
    for k in range(B):
        R, v, p, cov, jac = REFS[k]
        np.testing.assert_allclose(np.asarray(out.rot.matrix()[k]), R, atol=1e-5)
        np.testing.assert_allclose(out.vel[k], v, atol=1e-5)
        np.testing.assert_allclose(out.cov[k], cov, rtol=1e-3, atol=1e-5 * np.abs(cov).max())
        np.testing.assert_allclose(out.jac[k], jac, atol=1e-4)


def test_constant_rotation_rate_and_constant_acceleration_closed_forms():
    """ω constant, a = 0: ΔR = Exp(ωT) exactly (zero-order hold), J_R^g = −Jr(ωT)·T.
    a constant, ω = 0: Δv = aT, Δp = ½aT², and with accelerometer noise only
    Σ_vv = σ²T, Σ_vp = σ²T²/2, Σ_pp = σ²(T³/3 − T·dt²/12) (zero-order-hold sums),
    J_v^a = −T, J_p^a = −T²/2; with gyro noise only Σ_φφ = σ_g²T and
    Σ_vv = σ_g²·dt³·Σ_{j<n} j²·[a]×[a]×ᵀ."""
    n, dt = N, 0.005
    T = n * dt
    w = np.array([0.3, -0.5, 0.8])
    acc = np.array([0.7, -1.2, 9.81])
    s_g, s_a = 2e-3, 3e-2
    gyro = np.stack([np.tile(w, (n, 1)), np.zeros((n, 3)), np.zeros((n, 3))])
    accs = np.stack([np.zeros((n, 3)), np.tile(acc, (n, 1)), np.tile(acc, (n, 1))])
    z3 = np.zeros(3)
    out = run(gyro, accs, dt, sg=np.full(3, s_g), sa=z3, si=0.0)  # gyro noise only
    out_a = run(gyro, accs, dt, sg=z3, sa=np.full(3, s_a), si=0.0)  # accelerometer only
    eye = np.eye(3)
    # constant rate
    np.testing.assert_allclose(np.asarray(out.rot.matrix()[0]), ref.so3_exp(w * T), atol=1e-14)
    np.testing.assert_allclose(out.vel[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(out.pos[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(out.jac[0, 0:3, 0:3], -ref.right_jacobian(w * T) * T, atol=1e-13)
    # gyro noise of sample k reaches the end through ΔR_{k+1,n}ᵀ·Jr(ω dt)·dt
    jr = ref.right_jacobian(w * dt)
    expect = sum(ref.so3_exp(w * dt * m).T @ jr @ jr.T @ ref.so3_exp(w * dt * m)
                 for m in range(n)) * s_g**2 * dt
    np.testing.assert_allclose(out.cov[0, 0:3, 0:3], expect, rtol=1e-12, atol=1e-12 * s_g**2)
    # constant acceleration
    np.testing.assert_allclose(np.asarray(out.rot.matrix()[1]), eye, atol=1e-15)
    np.testing.assert_allclose(out.vel[1], acc * T, rtol=1e-14)
    np.testing.assert_allclose(out.pos[1], 0.5 * acc * T * T, rtol=1e-13)
    c = out_a.cov[1]
    np.testing.assert_allclose(c[3:6, 3:6], s_a**2 * T * eye, atol=1e-18, rtol=1e-12)
    np.testing.assert_allclose(c[3:6, 6:9], s_a**2 * T**2 / 2 * eye, atol=1e-18, rtol=1e-12)
    np.testing.assert_allclose(c[6:9, 6:9], s_a**2 * (T**3 / 3 - T * dt**2 / 12) * eye,
                               atol=1e-20, rtol=1e-12)
    np.testing.assert_allclose(c[0:3], 0.0, atol=1e-30)
    c = out.cov[1]
    np.testing.assert_allclose(c[0:3, 0:3], s_g**2 * T * eye, rtol=1e-12)
    ax = ref.skew(acc)
    np.testing.assert_allclose(c[3:6, 3:6], s_g**2 * dt**3 * (n - 1) * n * (2 * n - 1) / 6
                               * ax @ ax.T, rtol=1e-12, atol=1e-22)
    np.testing.assert_allclose(out.jac[1, 3:6, 3:6], -T * eye, atol=1e-15)
    np.testing.assert_allclose(out.jac[1, 6:9, 3:6], -T * T / 2 * eye, atol=1e-15)
    # a gyro bias δ tilts the rotation by −k·dt·δ before sample k: J_v^g = [a]×·dt²·Σk
    np.testing.assert_allclose(out.jac[1, 3:6, 0:3], ax * (T * T - T * dt) / 2, rtol=1e-12,
                               atol=1e-15)


def test_zero_motion_with_gravity_stays_at_rest():
    """A static IMU measures the specific force −Rᵀg; its deltas are gravity-free
    (Δv = −Rᵀg·T, Δp = −½Rᵀg·T²) and predict / dead_reckon keep the body at rest, for a
    level and two tilted attitudes."""
    g = np.array([0.0, 0.0, -9.81])
    R0 = np.stack([np.eye(3), ref.so3_exp(np.array([0.4, -0.7, 1.1])),
                   ref.so3_exp(np.array([-2.5, 0.3, 0.9]))])
    f = -np.einsum("bji,j->bi", R0, g)  # Rᵀ(−g)
    dt = 0.005
    T = N * dt
    accs = np.repeat(f[:, None], N, 1)
    pre = run(np.zeros((B, N, 3)), accs, dt)
    np.testing.assert_allclose(pre.vel, f * T, rtol=1e-13)
    np.testing.assert_allclose(pre.pos, 0.5 * f * T * T, rtol=1e-13)
    p0 = np.array([[1.0, 2.0, 3.0]] * B)
    start = NavState(SO3.from_matrix(jnp.asarray(R0)), jnp.zeros((B, 3)), p0)
    end = pre.predict(start, g)
    np.testing.assert_allclose(end.vel, 0.0, atol=1e-12)
    np.testing.assert_allclose(end.pos, p0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(end.rot.matrix()), R0, atol=1e-14)
    states = dead_reckon(np.zeros((B, N, 3)), accs, dt, g, start)
    assert states.pos.shape == (B, N, 3)
    np.testing.assert_allclose(states.vel, 0.0, atol=1e-12)
    np.testing.assert_allclose(states.pos, np.broadcast_to(p0[:, None], (B, N, 3)), atol=1e-12)


def test_dead_reckoning_matches_strapdown_loop():
    g, a, d, _, _ = BATCH
    grav = np.array([0.0, 0.0, -9.81])
    R0 = np.stack([ref.so3_exp(np.array([0.2, 0.1, -0.3]) * (k + 1)) for k in range(B)])
    v0 = np.array([[1.0, -0.5, 0.2]] * B)
    p0 = np.array([[3.0, 0.0, -1.0]] * B)
    init = NavState(SO3.from_matrix(jnp.asarray(R0)), v0, p0)
    states = dead_reckon(g, a, d, grav, init)
    for k in range(B):
        loop = ref.dead_reckoning(g[k], a[k], d[k], grav, R0[k], v0[k], p0[k])
        for n in (0, 17, N - 1):
            R, v, p = loop[n]
            np.testing.assert_allclose(np.asarray(states.rot.matrix()[k, n]), R, atol=1e-12)
            np.testing.assert_allclose(states.vel[k, n], v, atol=1e-11)
            np.testing.assert_allclose(states.pos[k, n], p, atol=1e-11)


def test_compose_equals_concatenated_window():
    g, a, d, bg, ba = BATCH
    h = N // 2
    left = run(g[:, :h], a[:, :h], d[:, :h], bg, ba)
    right = run(g[:, h:], a[:, h:], d[:, h:], bg, ba)
    whole = run(g, a, d, bg, ba)
    both = left @ right
    assert isinstance(both, Preintegrated)
    for name in ("vel", "pos", "dt", "cov", "jac"):
        np.testing.assert_allclose(getattr(both, name), getattr(whole, name), rtol=1e-10,
                                   atol=1e-13 * float(np.abs(getattr(whole, name)).max()))
    np.testing.assert_allclose(both.rot.data, whole.rot.data, atol=1e-14)


def test_first_order_bias_correction():
    """``corrected`` with new biases approaches re-preintegration with O(|δb|²) error and
    is exact (to rounding) in the accelerometer bias alone."""
    g, a, d, bg, ba = BATCH
    pre = run(g, a, d, bg, ba)
    errs = []
    for eps in (1e-3, 1e-4):
        dbg, dba = eps * np.array([1.0, -2.0, 0.5]), eps * np.array([3.0, 1.0, -2.0])
        again = run(g, a, d, bg + dbg, ba + dba)
        rot, vel, pos = pre.corrected(bg + dbg, ba + dba)
        errs.append(max(np.abs(np.asarray(rot.data - again.rot.data)).max(),
                        np.abs(np.asarray(vel - again.vel)).max(),
                        np.abs(np.asarray(pos - again.pos)).max()))
    assert errs[1] < errs[0] / 50, errs  # quadratic: 100x smaller for a 10x smaller step
    dba = np.array([0.3, -0.2, 0.1])
    again = run(g, a, d, bg, ba + dba)
    _, vel, pos = pre.corrected(None, ba + dba)
    np.testing.assert_allclose(vel, again.vel, atol=1e-13)
    np.testing.assert_allclose(pos, again.pos, atol=1e-13)


def test_module_equals_function():
    """(The module under ``jit`` and ``grad``: test_autodiff.py.)"""
    g, a, d, bg, ba = BATCH
    imu = ImuPreintegrator(gyro_noise=SIGMA_G, acc_noise=SIGMA_A, integration_noise=SIGMA_I,
                           gravity=(0.0, 0.0, -9.81))
    out = imu(g, a, d, bg, ba)
    expect = run(g, a, d, bg, ba)
    np.testing.assert_allclose(out.cov, expect.cov, rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(out.jac, expect.jac, rtol=1e-12, atol=1e-15)
    end = imu.predict(NavState.identity((B,)), out)
    np.testing.assert_allclose(end.vel, out.vel + imu.gravity * out.dt[:, None], atol=1e-12)
    states = imu.dead_reckon(g, a, d)
    assert states.pos.shape == (B, N, 3)


def test_accelerator_path_associative_scan_equals_cpu_blocked_scan(monkeypatch):
    """Prefix products run ``lax.associative_scan`` on accelerators and a blocked two-level
    scan on CPU; both give the same cumulative deltas, covariances and Jacobians."""
    from jaxpose.imu import _core

    g, a, d, _, _ = BATCH
    sv, sa = jnp.asarray(SIGMA_G**2), jnp.asarray(SIGMA_A**2)

    def both(g, a, d):
        vals = _core.prefix_values(g, a, d)
        full = _core.prefix(_core.samples(g, a, d, _core.Noise(sv, sa, jnp.asarray(0.0)), True))
        return vals, full

    cpu = jax.jit(lambda *x: both(*x))(g[0], a[0], d[0])  # fresh functions: no cache hits
    monkeypatch.setattr(_core.jax, "default_backend", lambda: "gpu")
    traced = []
    acc = jax.jit(lambda *x: traced.append(1) or both(*x))(g[0], a[0], d[0])
    assert traced
    for x, y in zip(jax.tree.leaves(cpu), jax.tree.leaves(acc), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-14 * float(np.abs(x).max()))
