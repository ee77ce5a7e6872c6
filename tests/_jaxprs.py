"""Walking traced programs in tests: every equation of a jaxpr and of the jaxprs inside it
(jit, loops, conditionals, custom derivative rules, linear solves)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from jax.extend import core as jex_core


def _subjaxprs(value: Any) -> Iterator[Any]:
    if isinstance(value, jex_core.ClosedJaxpr):
        yield value.jaxpr
    elif isinstance(value, jex_core.Jaxpr):
        yield value
    elif isinstance(value, (tuple, list)):
        for v in value:
            yield from _subjaxprs(v)


def equations(jaxpr: Any) -> Iterator[Any]:
    """Every equation of ``jaxpr`` and, recursively, of the jaxprs in its parameters."""
    for eqn in jaxpr.eqns:
        yield eqn
        for value in eqn.params.values():
            for sub in _subjaxprs(value):
                yield from equations(sub)
