"""Bad input: clear exceptions naming the argument (shapes and types at trace time; NaN
samples and non-positive dt at run time through ``eqx.error_if``, also under jit/vmap),
and the documented ``check=False`` status (bad values propagate as NaN)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.imu import (
    ImuPreintegrator,
    NavState,
    Preintegrated,
    dead_reckon,
    gps_factor,
    imu_factor,
    predict,
    preintegrate,
    read_imu_gps,
)
from jaxpose.io import FormatError
from jaxpose.lie import SE3, SO3

N = 8
G, A, DT = np.zeros((N, 3)), np.tile([0.0, 0.0, 9.81], (N, 1)), np.full(N, 0.01)


@pytest.mark.parametrize(
    "args, kwargs, match",
    [
        ((G[:5], A, DT), {}, "gyro has 5 samples but acc has 8"),
        ((G, A, DT[:5]), {}, r"preintegrate\(dt\): expected a scalar or 8 time steps"),
        ((G[:, :2], A, DT), {}, r"preintegrate\(gyro\): expected samples of shape"),
        ((G, A[0], DT), {}, r"preintegrate\(acc\): expected samples of shape"),
        ((G[:0], A[:0], DT[:0]), {}, "at least one sample"),
        ((np.zeros((2, N, 3)), np.zeros((3, N, 3)), DT), {}, "do not broadcast"),
        ((G, A, DT), {"gyro_bias": np.zeros(2)}, r"preintegrate\(gyro_bias\)"),
        ((G, A, DT), {"gyro_noise": np.ones(2)}, r"preintegrate\(gyro_noise\)"),
        ((G, A, DT), {"integration_noise": np.ones(3)}, r"preintegrate\(integration_noise\)"),
        ((G, A, DT), {"scheme": "euler"}, r"preintegrate\(scheme='euler'\)"),
        (("abc", A, DT), {}, r"preintegrate\(gyro\): expected an array of numbers"),
    ],
)
def test_shape_and_option_errors(args, kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        preintegrate(*args, **kwargs)


def test_complex_samples_rejected():
    with pytest.raises(TypeError, match="real floating"):
        preintegrate(G.astype(complex), A, DT)


@pytest.mark.parametrize(
    "bad, match",
    [
        ("nan_gyro", r"preintegrate\(gyro\): samples contain NaN or inf"),
        ("inf_acc", r"preintegrate\(acc\): samples contain NaN or inf"),
        ("zero_dt", r"preintegrate\(dt\): every time step must be positive"),
        ("negative_dt", r"preintegrate\(dt\): every time step must be positive"),
        ("nan_dt", r"preintegrate\(dt\): every time step must be positive"),
        ("inf_dt", r"preintegrate\(dt\): every time step must be positive and finite"),
    ],
)
def test_runtime_value_errors_under_jit_and_vmap(bad, match):
    g, a, d = G.copy(), A.copy(), DT.copy()
    if bad == "nan_gyro":
        g[3, 1] = np.nan
    elif bad == "inf_acc":
        a[2, 0] = np.inf
    elif bad == "zero_dt":
        d[4] = 0.0
    elif bad == "negative_dt":
        d[0] = -0.01
    elif bad == "inf_dt":
        d[1] = np.inf
    else:
        d[5] = np.nan
    # eagerly (blocking: on an accelerator the check's error arrives with the result)
    with pytest.raises(Exception, match=match):
        jax.block_until_ready(preintegrate(g, a, d))
    with pytest.raises(Exception, match=match):
        jax.block_until_ready(_checked(g, a, d))
    with pytest.raises(Exception, match=match):  # a bad window inside a batch
        jax.block_until_ready(_checked_batch(np.stack([G, g]), np.stack([A, a]),
                                             np.stack([DT, d])))


_checked = jax.jit(lambda g, a, d: preintegrate(g, a, d, gyro_noise=1e-3, acc_noise=1e-2).pos)
_checked_batch = jax.jit(jax.vmap(lambda g, a, d: preintegrate(g, a, d).pos))


def test_unchecked_bad_values_propagate_as_nan():
    """``check=False`` (documented): no run-time check; the outputs are NaN."""
    g = G.copy()
    g[0, 0] = np.nan
    out = preintegrate(g, A, DT, gyro_noise=1e-3, acc_noise=1e-2, check=False)
    assert np.isnan(np.asarray(out.rot.data)).all() and np.isnan(np.asarray(out.cov)).any()
    ok = preintegrate(G, A, DT, gyro_noise=1e-3, acc_noise=1e-2, check=False)
    assert np.all(np.isfinite(np.asarray(ok.cov)))


def test_predict_integrate_and_module_errors():
    pre = preintegrate(G, A, DT)
    state = NavState.identity()
    with pytest.raises(TypeError, match=r"predict\(state\): expected NavState"):
        predict(SE3.identity(), pre, [0.0, 0.0, -9.81])
    with pytest.raises(TypeError, match=r"predict\(pre\): expected Preintegrated"):
        predict(state, "pre", [0.0, 0.0, -9.81])
    with pytest.raises(ValueError, match=r"predict\(gravity\): expected a 3-vector"):
        predict(state, pre, [0.0, -9.81])
    with pytest.raises(ValueError, match=r"corrected\(gyro_bias\): expected shape"):
        pre.corrected(np.zeros(4))
    with pytest.raises(TypeError, match=r"dead_reckon\(init\): expected NavState"):
        dead_reckon(G, A, DT, [0.0, 0.0, -9.81], init=SE3.identity())
    with pytest.raises(ValueError, match=r"dead_reckon\(gyro, acc\): expected at least one"):
        dead_reckon(G[:0], A[:0], DT, [0.0, 0.0, -9.81])
    with pytest.raises(ValueError, match=r"dead_reckon: gyro has 5 samples but acc has 4"):
        dead_reckon(G[:5], A[:4], 0.01, [0.0, 0.0, -9.81])
    with pytest.raises(TypeError, match=r"NavState\(rot\): expected SO3"):
        NavState(np.zeros(4), np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match=r"NavState\(vel\): expected shape"):
        NavState(SO3.identity(), np.zeros(2), np.zeros(3))
    with pytest.raises(ValueError, match=r"ImuPreintegrator\(gravity\): expected a 3-vector"):
        ImuPreintegrator(gravity=9.81)
    with pytest.raises(ValueError, match=r"ImuPreintegrator\(scheme='rk4'\)"):
        ImuPreintegrator(scheme="rk4")
    with pytest.raises(ValueError, match="bias Jacobians were not computed"):
        _ = preintegrate(G, A, DT, bias_jacobians=False).d_vel_d_acc_bias
    with pytest.raises(ValueError, match="no covariance"):
        _ = pre.information
    with pytest.raises(TypeError, match=r"compose\(other\): expected Preintegrated"):
        pre.compose(3)
    with pytest.raises(ValueError, match="same outputs"):
        pre.compose(preintegrate(G, A, DT, bias_jacobians=False))
    assert isinstance(pre @ pre, Preintegrated)


def test_factor_errors():
    with_cov = preintegrate(np.stack([G, G]), np.stack([A, A]), DT, gyro_noise=1e-3,
                            acc_noise=1e-2)
    with pytest.raises(ValueError, match=r"imu_factor\(pre\): needs the covariance"):
        imu_factor(preintegrate(np.stack([G, G]), np.stack([A, A]), DT), [0, 1], [1, 2],
                   [0.0, 0.0, -9.81])
    with pytest.raises(ValueError, match=r"imu_factor\(i\): expected 2 integer indices"):
        imu_factor(with_cov, [0, 1, 2], [1, 2], [0.0, 0.0, -9.81])
    with pytest.raises(ValueError, match=r"imu_factor\(gravity\): expected a 3-vector"):
        imu_factor(with_cov, [0, 1], [1, 2], 9.81)
    with pytest.raises(ValueError, match=r"gps_factor: give exactly one of sigma"):
        gps_factor(np.zeros((2, 3)), [0, 1])
    with pytest.raises(ValueError, match=r"gps_factor\(sigma\): expected a positive"):
        gps_factor(np.zeros((2, 3)), [0, 1], sigma=-1.0)
    with pytest.raises(ValueError, match=r"gps_factor\(positions\): expected shape"):
        gps_factor(np.zeros((2, 2)), [0, 1], sigma=1.0)


@pytest.mark.parametrize(
    "text, match",
    [
        ("0,1,2,3,4,5,6\n", ":1: missing the initial-state row"),
        ("i,0,0,0,0,0,0,1,0,0,0\n0,1,2,3\n", ":2: IMU row: expected 6 numbers"),
        ("i,0,0,0,0,0,0,1,0,0,0\n0,1,2,3,4,5,x\n", ":2: IMU row: expected numbers"),
        ("i,0,0,0,0,0,0,1,0,0,0\n1,0,0,0,0,0,0,2\n", ":2: GPS row: quaternion"),
        ("i,0,0,0,0,0,0,1,0,0,0\n2,0,0,0\n", ":2: unknown row type '2'"),
        ("i,0,0,0,0,0,0,0,0,0,0\n0,1,2,3,4,5,6\n", ":1: initial-state row: no unit quat"),
        ("i,0,0,0,0,0,0,1,0,0,0\n", ":1: no IMU rows"),
        ("i,0,0,0,0,0,0,1,0,0,0\n0,1,2,3,4,5,nan\n", ":2: IMU row: non-finite"),
    ],
)
def test_reader_reports_file_and_line(tmp_path, text, match):
    path = tmp_path / "stream.csv"
    path.write_text(text)
    with pytest.raises(FormatError, match=match):
        read_imu_gps(path)


def test_biases_broadcast_and_dtype():
    """Biases broadcast with the samples' batch; integer samples become floats."""
    out = preintegrate(np.zeros((N, 3), int), A, DT, gyro_bias=np.zeros((2, 3)),
                       bias_jacobians=False)
    assert out.vel.shape == (2, 3) and jnp.issubdtype(out.vel.dtype, jnp.floating)


def test_zero_noise_covariance_and_information():
    """Zero noise densities: the covariance is well defined (zero), the information is
    infinite there, so requesting it raises (eagerly and under jit) instead of returning
    inf/NaN (it used to); so does imu_factor. Zero gyro noise alone makes it singular too."""
    pre = preintegrate(G, A, DT, gyro_noise=0.0, acc_noise=0.0)
    np.testing.assert_array_equal(pre.cov, np.zeros((9, 9)))
    match = "Preintegrated.information: the covariance is singular"
    with pytest.raises(Exception, match=match):
        _ = pre.information
    half = preintegrate(G, A, DT, gyro_noise=0.0, acc_noise=1e-2)
    assert np.all(np.isfinite(np.asarray(half.cov)))
    with pytest.raises(Exception, match=match):
        jax.block_until_ready(jax.jit(lambda p: p.information)(half))
    two = preintegrate(np.stack([G, G]), np.stack([A, A]), DT, gyro_noise=1e-3, acc_noise=1e-2)
    cov = np.asarray(two.cov).copy()
    cov[1] = 0.0  # the second window as with zero noise
    two = Preintegrated(two.rot, two.vel, two.pos, two.dt, jnp.asarray(cov), two.jac,
                        two.gyro_bias, two.acc_bias)
    with pytest.raises(ValueError, match=r"imu_factor\(pre\): the covariance of window 1"):
        imu_factor(two, [0, 1], [1, 2], [0.0, 0.0, -9.81])
    # the information of a regular covariance is its inverse
    reg = preintegrate(G, A, DT, gyro_noise=1e-3, acc_noise=1e-2)
    np.testing.assert_allclose(np.asarray(reg.information) @ np.asarray(reg.cov), np.eye(9),
                               atol=1e-8)


@pytest.mark.parametrize("scheme", ["manifold", "tangent"])
@pytest.mark.parametrize("what", ["gyro", "acc", "dt"])
def test_extreme_magnitudes_raise_instead_of_silent_nan(scheme, what):
    """Values of 1e200 overflow (gyro: the rotation angle's norm; acc: the covariance; dt:
    the position): a clear error, not NaN/inf outputs; check=False lets them through."""
    g, a, d = G.copy(), A.copy(), DT.copy()
    if what == "gyro":
        g[2] = 1e200
    elif what == "acc":
        a[2] = 1e200
    else:
        d[:] = 1e200
    with pytest.raises(Exception, match="preintegrate: the result overflows"):
        jax.block_until_ready(
            preintegrate(g, a, d, gyro_noise=1e-3, acc_noise=1e-2, scheme=scheme))
    out = preintegrate(g, a, d, gyro_noise=1e-3, acc_noise=1e-2, scheme=scheme, check=False)
    leaves = [out.rot.data, out.vel, out.pos, out.cov, out.jac]
    assert not all(np.all(np.isfinite(np.asarray(x))) for x in leaves)


def test_non_finite_noise_and_bias_raise():
    with pytest.raises(Exception, match=r"preintegrate\(gyro_noise\): contains NaN or inf"):
        jax.block_until_ready(preintegrate(G, A, DT, gyro_noise=np.nan, acc_noise=1e-2))
    with pytest.raises(Exception, match=r"preintegrate\(acc_bias\): contains NaN or inf"):
        jax.block_until_ready(preintegrate(G, A, DT, acc_bias=[0.0, np.inf, 0.0]))


@pytest.mark.parametrize(
    "bad, match",
    [
        ("zero_dt", r"preintegrate\(dt\): every time step must be positive and finite"),
        ("negative_dt", r"preintegrate\(dt\): every time step must be positive"),
        ("nan_dt", r"preintegrate\(dt\): every time step must be positive"),
        ("nan_gyro", r"preintegrate\(gyro\): samples contain NaN or inf"),
        ("inf_acc", r"preintegrate\(acc\): samples contain NaN or inf"),
        ("nan_bias", r"preintegrate\(gyro_bias\): contains NaN or inf"),
        ("overflow", r"preintegrate: the result overflows"),
    ],
)
def test_eager_value_errors_are_one_line_invalid_value_errors(bad, match):
    """Eagerly these surfaced as ``JaxRuntimeError: INTERNAL: CpuCallback error ...`` (the
    internal function is a jax.jit): now the class the lie groups' eager checks raise."""
    from jaxpose.lie import InvalidValueError

    g, a, d, kw = G.copy(), A.copy(), DT.copy(), {}
    if bad == "zero_dt":
        d = 0.0
    elif bad == "negative_dt":
        d[2] = -0.01
    elif bad == "nan_dt":
        d = float("nan")
    elif bad == "nan_gyro":
        g[3, 1] = np.nan
    elif bad == "inf_acc":
        a[2, 0] = np.inf
    elif bad == "nan_bias":
        kw = {"gyro_bias": [0.0, np.nan, 0.0]}
    else:
        a = a * 1e300
    with pytest.raises(InvalidValueError, match=match) as info:
        preintegrate(g, a, d, gyro_noise=1e-3, acc_noise=1e-2, **kw)
    assert isinstance(info.value, ValueError) and isinstance(info.value, RuntimeError)
    assert "\n" not in str(info.value) and "Callback" not in str(info.value)
    assert str(info.value).startswith("preintegrate")
    if bad != "overflow":  # (dead_reckon has no covariance to overflow)
        # through dead_reckon too, naming it (the messages named preintegrate, which the
        # user never called)
        with pytest.raises(InvalidValueError, match=match.replace("preintegrate",
                                                                   "dead_reckon")):
            dead_reckon(g, a, d, [0.0, 0.0, -9.81], **kw)
    # under the user's jax.jit the message still appears in the exception text
    with pytest.raises(Exception, match=match):
        jax.block_until_ready(_jit_pos(g, a, d, kw.get("gyro_bias")))


_jit_pos = jax.jit(lambda g, a, d, bg: preintegrate(g, a, d, gyro_bias=bg, gyro_noise=1e-3,
                                                    acc_noise=1e-2).pos)


def test_eager_valid_call_unchanged():
    """The eager path (flags returned, checked after the call) gives the jitted values."""
    rng = np.random.default_rng(0)
    g, a, d = rng.normal(size=(N, 3)), rng.normal(size=(N, 3)), np.full(N, 0.01)
    eager = preintegrate(g, a, d, gyro_noise=1e-3, acc_noise=1e-2)
    jitted = jax.jit(lambda g, a, d: preintegrate(g, a, d, gyro_noise=1e-3, acc_noise=1e-2))(
        g, a, d)
    for x, y in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-14, atol=1e-15)
