"""NumPy evaluation of the structural and integer primitives met by the sparsity analysis.

:mod:`jaxpose.optim._sparsity` evaluates copy primitives (slices, reshapes, gathers, ...)
on element-index arrays and folds small integer constants. Binding a primitive eagerly
compiles one XLA program per primitive and shape (~20–40 ms each on a CPU, about 0.7 s of
a cold ``least_squares`` trace); the primitives here are evaluated with NumPy instead,
with XLA's semantics (clamped dynamic-slice starts, C-style integer division, negative
and interior padding). :func:`host_eval` raises :class:`UnsupportedPrimitiveError` for
anything else, and the caller binds the primitive as before.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from jax.extend import core as jex_core


class UnsupportedPrimitiveError(Exception):
    """The primitive (or one inside a called jaxpr) has no NumPy rule here."""


def _integer_operands(a: np.ndarray, b: np.ndarray, name: str) -> None:
    """Integer operands with no zero divisor (XLA defines x/0 its own way: let it)."""
    if not np.issubdtype(np.result_type(a, b), np.integer) or np.any(b == 0):
        raise UnsupportedPrimitiveError(name)


def _int_div(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    _integer_operands(a, b, "div")
    q = np.abs(a) // np.abs(b)  # XLA: truncation towards zero
    return np.where((a < 0) != (b < 0), -q, q).astype(np.result_type(a, b))


def _int_rem(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    _integer_operands(a, b, "rem")
    return np.fmod(a, b)  # XLA: the sign of the dividend


_BINARY: dict[str, Callable[[Any, Any], Any]] = {
    "add": np.add, "add_any": np.add, "sub": np.subtract, "mul": np.multiply,
    "max": np.maximum, "min": np.minimum, "lt": np.less, "le": np.less_equal,
    "gt": np.greater, "ge": np.greater_equal, "eq": np.equal, "ne": np.not_equal,
    "and": np.bitwise_and, "or": np.bitwise_or, "xor": np.bitwise_xor,
    "div": _int_div, "rem": _int_rem,
}
_UNARY: dict[str, Callable[[Any], Any]] = {
    "neg": np.negative, "abs": np.abs, "sign": np.sign, "not": np.invert,
    "copy": np.copy, "copy_p": np.copy,
}


def _clamped_starts(shape: Sequence[int], sizes: Sequence[int], idx: Sequence[Any]
                    ) -> list[int]:
    starts = []
    for i, d, s in zip(idx, shape, sizes, strict=True):
        i = np.asarray(i)
        if i.dtype.kind == "u" and int(i) >= 2 ** (8 * i.itemsize - 1):
            # eager JAX clamps such an unsigned start; XLA's constant folding under jit
            # reads it as negative (uint8 200 → −56 → 0): no one answer to model (not
            # UnsupportedPrimitiveError, whose callers would bind the primitive eagerly)
            raise ValueError(f"unsigned start index {int(i)}: its meaning depends on jit")
        starts.append(int(min(max(int(i), 0), d - s)))
    return starts


def _pad(x: np.ndarray, value: Any, config: Sequence[tuple[int, int, int]]) -> np.ndarray:
    for axis, (lo, hi, interior) in enumerate(config):
        lo, hi, interior = int(lo), int(hi), int(interior)
        n = x.shape[axis]
        if interior and n > 1:
            shape = list(x.shape)
            shape[axis] = n + (n - 1) * interior
            y = np.full(shape, value, x.dtype)
            sl = [slice(None)] * x.ndim
            sl[axis] = slice(None, None, interior + 1)
            y[tuple(sl)] = x
            x = y
        sl = [slice(None)] * x.ndim
        sl[axis] = slice(max(-lo, 0), x.shape[axis] - max(-hi, 0))
        x = x[tuple(sl)]
        widths = [(0, 0)] * x.ndim
        widths[axis] = (max(lo, 0), max(hi, 0))
        x = np.pad(x, widths, constant_values=value)
    return x


def _eval_one(name: str, args: list[np.ndarray], p: dict[str, Any]) -> list[Any]:
    if name in _BINARY:
        return [_BINARY[name](args[0], args[1])]
    if name in _UNARY:
        return [_UNARY[name](args[0])]
    if name == "convert_element_type":
        x = np.asarray(args[0])
        new = np.dtype(p["new_dtype"])
        if np.issubdtype(x.dtype, np.inexact) and np.issubdtype(new, np.integer):
            info = np.iinfo(new)  # XLA saturates out-of-range values, NumPy wraps them
            if not np.all((x > info.min - 1) & (x < info.max + 1)):  # NaN/Inf too
                raise UnsupportedPrimitiveError(name)
        return [x.astype(new)]
    if name == "select_n":
        which, cases = args[0], args[1:]
        return [np.choose(np.asarray(which, np.int64), np.broadcast_arrays(*cases))
                if len(cases) > 1 else cases[0]]
    if name == "clamp":
        return [np.clip(args[1], args[0], args[2])]
    if name == "iota":
        shape, dim = tuple(p["shape"]), int(p["dimension"])
        r = np.arange(shape[dim], dtype=p["dtype"])
        return [np.broadcast_to(r.reshape([-1 if a == dim else 1 for a in range(len(shape))]),
                                shape).copy()]
    if name == "reshape":
        if p.get("dimensions") is not None:
            raise UnsupportedPrimitiveError(name)
        return [np.reshape(args[0], tuple(p["new_sizes"]))]
    if name == "broadcast_in_dim":
        shape, dims = tuple(p["shape"]), tuple(p["broadcast_dimensions"])
        src = np.reshape(args[0], [args[0].shape[dims.index(a)] if a in dims else 1
                                   for a in range(len(shape))])
        return [np.broadcast_to(src, shape).copy()]
    if name == "transpose":
        return [np.transpose(args[0], tuple(p["permutation"]))]
    if name == "squeeze":
        return [np.squeeze(args[0], tuple(p["dimensions"]))]
    if name == "expand_dims":
        return [np.expand_dims(args[0], tuple(p["dimensions"]))]
    if name == "rev":
        return [np.flip(args[0], tuple(p["dimensions"]))]
    if name == "slice":
        strides = p["strides"] or (1,) * args[0].ndim
        return [args[0][tuple(slice(int(a), int(b), int(s)) for a, b, s in
                              zip(p["start_indices"], p["limit_indices"], strides, strict=True))]]
    if name == "concatenate":
        return [np.concatenate(args, axis=int(p["dimension"]))]
    if name == "stack":
        return [np.stack(args, axis=int(p["axis"]))]
    if name == "split":
        cuts = np.cumsum([int(s) for s in p["sizes"]])[:-1]
        return list(np.split(args[0], cuts, axis=int(p["axis"])))
    if name == "pad":
        return [_pad(args[0], args[1], p["padding_config"])]
    if name == "dynamic_slice":
        x, sizes = args[0], tuple(p["slice_sizes"])
        starts = _clamped_starts(x.shape, sizes, args[1:])
        return [x[tuple(slice(s, s + n) for s, n in zip(starts, sizes, strict=True))].copy()]
    if name == "dynamic_update_slice":
        x, upd = args[0].copy(), args[1]
        starts = _clamped_starts(x.shape, upd.shape, args[2:])
        x[tuple(slice(s, s + n) for s, n in zip(starts, upd.shape, strict=True))] = upd
        return [x]
    if name in ("jit", "pjit"):
        closed = p["jaxpr"]
        return eval_jaxpr(closed.jaxpr, [np.asarray(c) for c in closed.consts], args)
    raise UnsupportedPrimitiveError(name)


def host_eval(eqn: Any, args: Sequence[Any], *, cast: bool = True) -> list[np.ndarray]:
    """The outputs of ``eqn`` applied to concrete ``args`` (NumPy arrays), checked against
    the output shapes and cast to the output dtypes (``cast=False`` keeps the arguments'
    dtype: copy primitives applied to index arrays); raises
    :class:`UnsupportedPrimitiveError` where it has no rule (or NumPy's answer differs
    from XLA's: a float out of an integer type's range), ``ValueError`` where XLA's own
    answer differs with and without jit (an unsigned dynamic-slice start ≥ 2^(bits−1))."""
    arrays = [np.asarray(a) for a in args]
    outs = _eval_one(eqn.primitive.name, arrays, eqn.params)
    result = []
    for o, v in zip(outs, eqn.outvars, strict=True):
        o = np.asarray(o)
        if cast:
            o = o.astype(v.aval.dtype, copy=False)
        if o.shape != tuple(v.aval.shape):
            raise UnsupportedPrimitiveError(
                f"{eqn.primitive.name}: shape {o.shape} != {v.aval.shape}")
        result.append(o)
    return result


def eval_jaxpr(jaxpr: Any, consts: Sequence[Any], args: Sequence[Any]) -> list[np.ndarray]:
    """Evaluate a jaxpr with :func:`host_eval` (raises :class:`UnsupportedPrimitiveError`)."""
    env: dict[Any, Any] = {}
    for v, x in zip((*jaxpr.constvars, *jaxpr.invars), (*consts, *args), strict=True):
        env[v] = np.asarray(x)

    def read(x: Any) -> Any:
        return np.asarray(x.val) if isinstance(x, jex_core.Literal) else env[x]

    for eqn in jaxpr.eqns:
        for v, o in zip(eqn.outvars, host_eval(eqn, [read(x) for x in eqn.invars]), strict=True):
            env[v] = o
    return [read(v) for v in jaxpr.outvars]


__all__ = ["UnsupportedPrimitiveError", "eval_jaxpr", "host_eval"]
