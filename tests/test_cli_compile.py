"""``jaxpose.compile_options``: the fusion-emitter option on the CPU when XLA knows it,
nothing where it does not; the CLI compiles its solvers with it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpose as jp
from jaxpose import _compile, cli

# the options are XLA:CPU's; an accelerator's default backend gets none (tested below)
cpu_only = pytest.mark.skipif(jax.default_backend() != "cpu", reason="XLA:CPU options")


@cpu_only
def test_compile_options_on_this_cpu_compile_the_same_program():
    opts = jp.compile_options()
    assert opts == {"xla_cpu_use_fusion_emitters": False}  # CI and this machine: XLA:CPU
    f = lambda x: jnp.sin(x) * 2.0  # noqa: E731
    np.testing.assert_allclose(jax.jit(f, compiler_options=opts)(jnp.arange(4.0)),
                               2.0 * np.sin(np.arange(4.0)), rtol=1e-6)
    lowered = jax.jit(lambda x: x + 1.0).lower(jnp.arange(3.0))
    np.testing.assert_allclose(cli._compile(lowered)(jnp.arange(3.0)), np.arange(3.0) + 1.0)
    opts["mutated"] = True  # a copy: the cached answer is not changed
    assert "mutated" not in jp.compile_options()


def test_an_xla_without_the_option_gets_no_options(monkeypatch):
    monkeypatch.setattr(_compile, "_CPU_OPTIONS", {"xla_no_such_option_zz": False})
    _compile._supported.cache_clear()
    try:
        assert jp.compile_options() == {}
        lowered = jax.jit(lambda x: x * 3.0).lower(jnp.arange(3.0))
        np.testing.assert_allclose(cli._compile(lowered)(jnp.arange(3.0)), 3.0 * np.arange(3.0))
    finally:
        _compile._supported.cache_clear()


def test_other_backends_get_no_options():
    assert _compile._supported("gpu", (("xla_cpu_use_fusion_emitters", False),)) == ()


@cpu_only
def test_whole_loop_flags_add_the_ynn_option(monkeypatch):
    """With the whole-loop flags in XLA_FLAGS the options also turn YNNPACK's dot fusions
    off where this XLA knows that option; an unknown one is dropped, not fatal."""
    monkeypatch.setenv("XLA_FLAGS", _compile.WHOLE_LOOP_FLAGS)
    assert jp.compile_options() == {"xla_cpu_use_fusion_emitters": False,
                                    "xla_cpu_experimental_ynn_fusion_type": ""}
    monkeypatch.setattr(_compile, "_WHOLE_LOOP_OPTIONS", {"xla_no_such_option_zz": ""})
    assert jp.compile_options() == {"xla_cpu_use_fusion_emitters": False}
    monkeypatch.delenv("XLA_FLAGS")
    assert jp.compile_options() == {"xla_cpu_use_fusion_emitters": False}
