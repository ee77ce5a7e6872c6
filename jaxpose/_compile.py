"""XLA compiler options that shorten the compilation of jaxpose's solvers.

XLA:CPU's newer fusion emitters generate code for the large fused loops of a solver and
its derivatives more slowly than the classic emitters: without them a cold
``jax.jit(jax.grad(...))`` through ``least_squares`` or ``graph.solve`` compiles 20–30 %
faster (``bench/compile.py``). The compiled code is not always as fast: the same for the
dense least-squares entries and within 5 % for the ``jaxpose pgo`` solves (parking-garage,
smallGrid3D), but up to 25 % slower for a graph solve that differentiates its factors by
autodiff (``bench/compile.py``'s ``graph_solve``). So they pay off where compilation
dominates (notebooks, one-shot jobs such as the ``jaxpose`` command, which uses them) and
not in a long training loop. They are XLA *debug* options: jaxpose never sets them behind
a user's back; pass them to your own ``jax.jit``::

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
