"""predict's gravity and biases: a list gravity turned float32 data into a float64
velocity and position beside a float32 rotation, and a NaN gravity or bias component
passed through into the state without a word."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose import imu
from jaxpose.lie import SO3, InvalidValueError

G = [0.0, 0.0, -9.81]


def _window(dtype):
    n = 20
    t = np.arange(n) * 0.01
    gyro = np.stack([0.1 + 0 * t, 0.2 * np.sin(t), 0.05 + 0 * t], 1)
    acc = np.stack([0.3 + 0 * t, 0.0 * t, 9.81 + 0.1 * np.cos(t)], 1)
    pre = imu.preintegrate(jnp.asarray(gyro, dtype), jnp.asarray(acc, dtype),
                           jnp.full((n,), 0.01, dtype))
    state = imu.NavState(SO3.identity(dtype=dtype), jnp.asarray([1.0, 0.0, 0.0], dtype),
                         jnp.zeros(3, dtype))
    return pre, state


def test_list_gravity_keeps_float32_data_in_float32():
    jax.config.update("jax_enable_x64", True)
    pre, state = _window(jnp.float32)
    out = imu.predict(state, pre, G)
    assert {out.rot.data.dtype, out.vel.dtype, out.pos.dtype} == {jnp.dtype(jnp.float32)}
    reckoned = imu.dead_reckon(np.zeros((3, 3), np.float32), np.zeros((3, 3), np.float32),
                               np.full(3, 0.1, np.float32), G)
    assert reckoned.vel.dtype == jnp.float32 and reckoned.pos.dtype == jnp.float32
    # the same numbers as float64 data (independent of the cast: v = v0 + g t + R Δv)
    pre64, state64 = _window(jnp.float64)
    ref = imu.predict(state64, pre64, np.asarray(G))
    np.testing.assert_allclose(out.vel, ref.vel, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(out.pos, ref.pos, rtol=1e-5, atol=1e-6)
    t, g = float(pre64.dt), np.asarray(G)  # identity start: p = p0 + v0 t + ½ g t² + Δp
    np.testing.assert_allclose(ref.pos, state64.pos + state64.vel * t + 0.5 * g * t * t
                               + pre64.pos, atol=1e-12)


@pytest.mark.parametrize("where", ["gravity", "gyro_bias", "acc_bias"])
def test_non_finite_gravity_or_bias_raises_eagerly_and_under_jit(where):
    jax.config.update("jax_enable_x64", True)
    pre, state = _window(jnp.float64)
    bad = jnp.array([0.0, jnp.nan, 0.0])
    kw = {"gravity": jnp.asarray(G), "gyro_bias": jnp.zeros(3), "acc_bias": jnp.zeros(3)}
    kw[where] = bad
    with pytest.raises(InvalidValueError, match=rf"{where}\): expected finite"):
        imu.predict(state, pre, **kw)
    with pytest.raises(Exception, match=rf"{where}\): expected finite"):
        jax.block_until_ready(jax.jit(lambda k: imu.predict(state, pre, **k))(kw))
    # finite values under jit: same answer as eagerly
    kw[where] = jnp.array([0.0, 0.01, 0.0])
    eager = imu.predict(state, pre, **kw)
    jitted = jax.jit(lambda k: imu.predict(state, pre, **k))(kw)
    np.testing.assert_allclose(jitted.pos, eager.pos, rtol=1e-12)
