"""XLA compiler options that shorten the compilation of jaxpose's solvers.

XLA:CPU's newer fusion emitters generate code for the large fused loops of a solver and
its derivatives more slowly than the classic emitters, at the same run time: without them
a cold ``jax.jit(jax.grad(...))`` through ``least_squares`` or ``graph.solve`` compiles
20–30 % faster (``bench/compile.py``; parking-garage, sphere2500, smallGrid3D and intel
solve at the same speed). They are XLA *debug* options, so jaxpose never sets them
behind a user's back: pass them to your own ``jax.jit`` (the ``jaxpose`` command does)::

    step = jax.jit(jax.grad(loss), compiler_options=jaxpose.compile_options())
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import numpy as np

_CPU_OPTIONS: dict[str, Any] = {"xla_cpu_use_fusion_emitters": False}


def compile_options() -> dict[str, Any]:
    """Options for ``jax.jit(..., compiler_options=...)`` / ``lowered.compile(...)`` on the
    default backend: ``{"xla_cpu_use_fusion_emitters": False}`` on a CPU whose XLA knows
    that option (checked once by compiling a one-operation program), else ``{}``."""
    return dict(_supported(jax.default_backend()))


@functools.cache
def _supported(backend: str) -> tuple[tuple[str, Any], ...]:
    if backend != "cpu":
        return ()
    try:
        jax.jit(lambda x: x + 1).lower(np.float32(0)).compile(compiler_options=_CPU_OPTIONS)
    except jax.errors.JaxRuntimeError:  # an XLA without the option: its defaults
        return ()
    return tuple(_CPU_OPTIONS.items())


__all__ = ["compile_options"]
