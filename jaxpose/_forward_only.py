"""Values whose derivative exists in forward mode only, with a clear error in reverse mode.

A ``lax.while_loop`` (a solver that stops at convergence) has a forward-mode derivative
(``jvp``, ``jacfwd``) but none in reverse mode (``grad``, ``jacrev``, ``vjp``): JAX raises
an error about ``while_loop`` that does not say which jaxpose function or option to use
instead. :func:`forward_mode_only` passes values through unchanged, their tangents too, and
raises ``NotImplementedError`` with the caller's message when reverse mode transposes them
(at trace time, before JAX reaches the loop).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

_identity = Primitive("jaxpose_forward_mode_only")
_identity.def_impl(lambda x, *, message: x)
_identity.def_abstract_eval(lambda x, *, message: x)
mlir.register_lowering(_identity, lambda ctx, x, *, message: [x])
batching.primitive_batchers[_identity] = lambda args, dims, *, message: (
    _identity.bind(args[0], message=message), dims[0])


def _jvp(primals: tuple[Any], tangents: tuple[Any], *, message: str) -> tuple[Any, Any]:
    (x,), (t,) = primals, tangents
    out = _identity.bind(x, message=message)
    if type(t) is ad.Zero:
        return out, t
    return out, _identity.bind(t, message=message)


def _transpose(ct: Any, x: Any, *, message: str) -> Any:
    raise NotImplementedError(message)


ad.primitive_jvps[_identity] = _jvp
ad.primitive_transposes[_identity] = _transpose


def forward_mode_only(tree: Any, message: str) -> Any:
    """``tree`` unchanged; reverse-mode differentiation through its floating-point leaves
    raises ``NotImplementedError(message)`` (forward mode, ``jit`` and ``vmap`` work)."""
    return jax.tree.map(
        lambda x: _identity.bind(x, message=message) if eqx.is_inexact_array(x) else x, tree)


__all__ = ["forward_mode_only"]
