"""Robust-kernel parameters outside their domain raise, whatever form the value takes.

The construction check looked at Python int/float only: ``Huber(jnp.array(-1.0))`` or
``Huber(np.float32(-1.0))`` gave ρ(4) = −5 (a negative cost) and ``least_squares`` then
returned the initial params with status CONVERGED. Known values (Python and NumPy numbers,
NumPy and concrete JAX arrays) raise on construction; traced ones (a learned δ under
jit/grad/vmap) are checked by ``least_squares`` at run time and still differentiate."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose.optim as jo

DELTA_KERNELS = [jo.Huber, jo.PseudoHuber, jo.Cauchy, jo.SoftLOne, jo.Arctan, jo.Scale,
                 jo.Tukey, jo.GemanMcClure, jo.Welsch]
BAD_DELTAS = {
    "jnp_negative": jnp.array(-1.0),
    "np_float32_negative": np.float32(-1.0),
    "np_array_zero": np.array(0.0),
    "jnp_nan": jnp.array(np.nan),
    "np_array_one_negative": np.array([1.0, -2.0]),
    "python_zero": 0.0,
}


@pytest.mark.parametrize("kernel", DELTA_KERNELS, ids=lambda k: k.__name__)
@pytest.mark.parametrize("value", list(BAD_DELTAS.values()), ids=list(BAD_DELTAS))
def test_known_non_positive_delta_raises(kernel, value):
    with pytest.raises(ValueError, match=rf"{kernel.__name__}\(delta=.*delta has to be positive"):
        kernel(value)


@pytest.mark.parametrize("kernel", DELTA_KERNELS, ids=lambda k: k.__name__)
def test_known_positive_delta_accepted(kernel):
    for value in (jnp.array(0.5), np.float32(2.0), np.array([0.5, 1.0]), 3):
        kernel(value)


def test_tolerant_parameters():
    for a in (jnp.array(-1.0), np.float32(-0.5), -1):
        with pytest.raises(ValueError, match=r"Tolerant\(a=.*a has to be non-negative"):
            jo.Tolerant(a, -1.0)
    for b in (jnp.array(0.0), np.float64(0.0), np.zeros(2), 0):
        with pytest.raises(ValueError, match=r"Tolerant\(b=.*b has to be non-zero"):
            jo.Tolerant(1.0, b)
    jo.Tolerant(jnp.array(0.0), jnp.array(-1.0))
    jo.Tolerant(np.float32(2.0), np.float32(0.5))


def test_non_numeric_parameter_raises():
    with pytest.raises(TypeError, match=r"Huber\(delta='a'\): expected a number"):
        jo.Huber("a")


# minimiser of 0.5 Σ ρ((p − a_i)²) with Huber(δ), a = [0, 0.5, 10], 0 < δ < 9: the two
# first residuals are inliers, the third an outlier with constant gradient δ·sign, so
# p + (p − 0.5) − δ = 0: p = (0.5 + δ) / 2, dp/dδ = 1/2 (closed form).
A = jnp.array([[0.0], [0.5], [10.0]])


def _solve(delta):
    return jo.least_squares(lambda p, a: p - a, jnp.zeros(1), A, kernel=jo.Huber(delta),
                            cost_rtol=1e-14).params[0]


def test_negative_delta_array_no_longer_gives_a_wrong_solution():
    with pytest.raises(ValueError, match=r"Huber\(delta=.*has to be positive"):
        jo.least_squares(lambda p, a: p - a, jnp.zeros(1), A, kernel=jo.Huber(jnp.array(-1.0)))
    # a valid array δ: the closed-form minimiser
    np.testing.assert_allclose(float(_solve(jnp.array(1.0))), 0.75, rtol=1e-6)


def test_traced_delta_is_checked_at_run_time():
    msg = r"Huber\(delta\): delta has to be positive"
    with pytest.raises(Exception, match=msg):  # the user's jax.jit
        jax.block_until_ready(jax.jit(_solve)(-1.0))
    with pytest.raises(Exception, match=msg):  # eager grad: a JVP tracer
        jax.grad(_solve)(-1.0)
    with pytest.raises(Exception, match=msg):  # one bad δ in a batch
        jax.block_until_ready(jax.vmap(_solve)(jnp.array([1.0, -2.0])))


def test_traced_delta_still_differentiates():
    """A learned kernel scale: the check adds no error and keeps the derivative."""
    for delta in (1.0, 2.0):
        p, g = jax.jit(jax.value_and_grad(_solve))(delta)
        np.testing.assert_allclose(float(p), (0.5 + delta) / 2, rtol=1e-6)
        np.testing.assert_allclose(float(g), 0.5, rtol=1e-6)
    ps = jax.vmap(_solve)(jnp.array([1.0, 2.0]))
    np.testing.assert_allclose(np.asarray(ps), [0.75, 1.25], rtol=1e-6)
