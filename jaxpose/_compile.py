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

The ``jaxpose pgo`` command also sets :data:`WHOLE_LOOP_FLAGS` (a process-wide XLA
backend option, read when JAX starts its backend; :func:`compile_options` then turns
YNNPACK's dot fusions off): XLA:CPU then compiles a ``while`` loop whose body holds no
library call (LAPACK, YNNPACK, a host callback) and touches at most
:data:`WHOLE_LOOP_BYTES` bytes into one function, instead of dispatching each of its
operations separately (~0.1 µs each, ~190 per Levenberg–Marquardt iteration of a tiny pose
graph). :func:`loops_compile_whole` tells whether that is in effect for programs compiled
with :func:`compile_options` (XLA's newer fusion emitters keep a scatter, so a loop,
split); the graph solver then factorises small dense systems without LAPACK
(:func:`jaxpose.graph._linear.cholesky_solve_loops`) so that its whole loop compiles into
one function (pose3example 19 → 9 µs per iteration). Call :func:`use_whole_loops` before
JAX starts, and compile with :func:`compile_options`, to get the same in your process.
"""

from __future__ import annotations

import functools
import os
from typing import Any

import jax
import numpy as np

_CPU_OPTIONS: dict[str, Any] = {"xla_cpu_use_fusion_emitters": False}


WHOLE_LOOP_BYTES = 1 << 22
"""Bytes a loop may touch (XLA's cost analysis of its body) to compile into one function."""

_THRESHOLD = "xla_cpu_small_while_loop_byte_threshold"

WHOLE_LOOP_FLAGS = f"--xla_backend_extra_options={_THRESHOLD}={WHOLE_LOOP_BYTES}"
"""An XLA backend option (one an XLA does not know is ignored; an unknown flag would abort
the process): loops touching at most :data:`WHOLE_LOOP_BYTES` compile into one function."""

# With the flag, compile_options() also turns off YNNPACK's dot fusions: library calls,
# one in a loop keeps it split. A compile option, so an XLA without it raises (and is
# probed) instead of aborting.
_WHOLE_LOOP_OPTIONS: dict[str, Any] = {"xla_cpu_experimental_ynn_fusion_type": ""}


def _whole_loop_flag() -> bool:
    """Whether :data:`WHOLE_LOOP_FLAGS`'s option is in this process's ``XLA_FLAGS``."""
    return _THRESHOLD in os.environ.get("XLA_FLAGS", "")


def use_whole_loops() -> None:
    """Append :data:`WHOLE_LOOP_FLAGS` to ``XLA_FLAGS`` (the ``jaxpose pgo`` command's
    setting). Takes effect only if JAX has not started its backend yet; left alone when
    ``XLA_FLAGS`` already sets ``xla_backend_extra_options`` (the user's choice)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_extra_options" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {WHOLE_LOOP_FLAGS}".strip()


@functools.cache
def loops_compile_whole() -> bool:
    """Whether this process's XLA, with :func:`compile_options`, compiles a loop of this
    library's small dense solves into one function (:data:`WHOLE_LOOP_FLAGS` in effect on
    a CPU backend), checked once by compiling a probe loop with the operations that keep
    one split otherwise (a scatter-add, which XLA's newer fusion emitters keep out, and
    the identity product of :func:`jaxpose.lie.series.computed_once`, a YNNPACK call)."""
    if jax.default_backend() != "cpu" or not _whole_loop_flag():
        return False  # without the flag XLA's threshold (1 KiB) cannot pass the probe
    from .lie.series import computed_once

    def probe(x: jax.Array, index: jax.Array) -> jax.Array:
        def body(_: Any, y: jax.Array) -> jax.Array:
            return computed_once(y * 0.5 + 1.0)[0].at[index].add(1.0)

        return jax.lax.fori_loop(0, 2, body, x)

    lowered = jax.jit(probe).lower(np.zeros((64, 64)), np.zeros(8, np.int32))
    text = lowered.compile(compiler_options=compile_options()).as_text()
    return "xla_cpu_small_call" in text and " while(" not in _entry(text)


def _entry(hlo: str) -> str:
    """The ENTRY computation of an HLO module's text."""
    return hlo[hlo.index("ENTRY"):] if "ENTRY" in hlo else hlo


def compile_options() -> dict[str, Any]:
    """Options for ``jax.jit(..., compiler_options=...)`` / ``lowered.compile(...)`` on the
    default backend: ``{"xla_cpu_use_fusion_emitters": False}`` on a CPU whose XLA knows
    that option (checked once by compiling a one-operation program), else ``{}``; with
    :data:`WHOLE_LOOP_FLAGS` in ``XLA_FLAGS``, also no YNNPACK dot fusions (where known)."""
    backend = jax.default_backend()
    options = dict(_supported(backend, tuple(_CPU_OPTIONS.items())))
    if _whole_loop_flag():
        options.update(_supported(backend, tuple(_WHOLE_LOOP_OPTIONS.items())))
    return options


@functools.cache
def _supported(backend: str, options: tuple[tuple[str, Any], ...]) -> tuple[tuple[str, Any], ...]:
    """``options`` where this backend's XLA compiles with them (CPU only), else ()."""
    if backend != "cpu":
        return ()
    try:
        jax.jit(lambda x: x + 1).lower(np.float32(0)).compile(compiler_options=dict(options))
    except jax.errors.JaxRuntimeError:  # an XLA without the option: its defaults
        return ()
    return options


__all__ = ["compile_options"]
