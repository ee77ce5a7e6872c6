"""The CLI's solver compile options: applied on the CPU, and an XLA that does not know
them compiles with its defaults instead of failing."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxpose import cli


def test_compile_applies_the_options_and_falls_back_when_unknown(monkeypatch):
    lowered = jax.jit(lambda x: jnp.sin(x) * 2.0).lower(jnp.arange(4.0))
    np.testing.assert_allclose(cli._compile(lowered)(jnp.arange(4.0)),
                               2.0 * np.sin(np.arange(4.0)), rtol=1e-6)
    monkeypatch.setattr(cli, "_SOLVER_COMPILE_OPTIONS", {"xla_no_such_option_zz": False})
    lowered = jax.jit(lambda x: x + 1.0).lower(jnp.arange(3.0))
    np.testing.assert_allclose(cli._compile(lowered)(jnp.arange(3.0)), np.arange(3.0) + 1.0)
