"""Structural sparsity of a Jacobian by dependency analysis of its JVP jaxpr.

``jacobian_pattern(f, x)`` returns the (m, n) boolean pattern of ∂f/∂x for
``f: (n,) -> (m,)``: entry (i, j) is set when output i's tangent can depend on input j's
tangent in the program ``jax.jvp`` traces for f. The analysis runs on that *linearised*
program (so custom JVP rules and JAX's symbolic zeros are what counts) and is value
independent: both sides of a ``select_n``/``where`` and every branch of a ``cond`` count,
numerically zero partial derivatives (x·y at y = 0) count, and any primitive it does not
model makes each of its outputs depend on all of its inputs. The pattern is therefore a
superset of the nonzeros of the Jacobian at *every* point and for every value of traced
arguments (conservative, never missing an entry); it is exact for the elementwise,
indexing, reduction and contraction primitives the Lie-group code uses, and sees into
calls (``jit``, ``checkpoint``, ``custom_jvp``); loops are conservative. Index operands
(gather, dynamic_slice) must be compile-time constants for an exact answer; traced
indices make the affected outputs depend on the whole operand.

Dependencies are kept as scipy CSR boolean matrices (elements × n), one per variable.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jax import core
from jax.extend import core as jex_core

from ._host_eval import UnsupportedPrimitiveError, host_eval

Dep = sp.csr_matrix | None  # None: depends on no input tangent

_ELEMENTWISE = frozenset(
    """add add_any sub mul div neg max min select_n convert_element_type sqrt rsqrt cbrt
    exp exp2 log log1p expm1 sin cos tan tanh sinh cosh asin acos atan asinh acosh atanh
    atan2 abs sign pow integer_pow square logistic erf erfc erf_inv rem nextafter clamp
    copy copy_p reduce_precision real imag conj complex floor ceil round is_finite
    stop_gradient pjit_elementwise""".split()
)
_COPY_ONE = frozenset(
    "reshape broadcast_in_dim transpose squeeze expand_dims rev slice".split()
)
_COPY_ALL = frozenset(["concatenate", "stack"])
_REDUCE = frozenset(["reduce_sum", "reduce_max", "reduce_min", "reduce_prod"])
# primitives that apply their sub-program once to their operands (a call): analysed
# inside. Others with a sub-program are not calls — scan and fori_loop run theirs once
# per step on slices and a carry, shard_map on shards — and get the conservative answer
# (analysed as a call, a scan's pattern missed entries: a wrong Jacobian, silently)
_CALLS = frozenset(
    """jit pjit closed_call core_call eval_jaxpr remat2 checkpoint custom_jvp_call
    custom_vjp_call custom_vjp_call_jaxpr xla_metadata_call""".split()
)
_MAX_EVAL = 1 << 20  # largest constant (elements) folded on the host


def _size(aval: Any) -> int:
    return int(np.prod(aval.shape, dtype=np.int64))


def _union(deps: list[Dep], size: int, n: int) -> Dep:
    """Elementwise OR of dependency matrices (a 1-element one broadcasts)."""
    acc: Dep = None
    for d in deps:
        if d is None:
            continue
        if d.shape[0] != size:  # a one-element operand broadcasts
            d = _dense_dep(d, size, n)
        acc = d if acc is None else (acc + d)
    return None if acc is None else _clean(acc)


def _clean(d: sp.csr_matrix) -> sp.csr_matrix:
    d = d.tocsr()
    d.data = np.ones_like(d.data, dtype=bool)
    d.eliminate_zeros()
    return d.astype(bool)


def _dense_dep(d: sp.csr_matrix, size: int, n: int) -> sp.csr_matrix:
    """Every one of ``size`` outputs depends on every input any row of ``d`` depends on."""
    cols = np.unique(d.indices)
    return sp.csr_matrix(
        (np.ones(size * cols.size, bool), np.tile(cols, size),
         np.arange(0, size * cols.size + 1, max(cols.size, 1))
         if cols.size else np.zeros(size + 1, np.int64)),
        shape=(size, n),
    )


def _broadcast(d: Dep, shape: tuple[int, ...], out: tuple[int, ...]) -> Dep:
    """Dependencies of an operand broadcast (numpy rules) to the output shape."""
    if d is None or shape == out:
        return d
    idx = np.arange(int(np.prod(shape, dtype=np.int64))).reshape(shape)
    return _gather_rows(d, np.broadcast_to(idx, out))


def _gather_rows(d: sp.csr_matrix, idx: np.ndarray) -> sp.csr_matrix:
    """Rows ``idx`` of ``d`` (index −1: an empty row)."""
    idx = np.asarray(idx, np.int64).reshape(-1)
    pad = sp.vstack([d, sp.csr_matrix((1, d.shape[1]), dtype=bool)]).tocsr()
    return _clean(pad[np.where(idx < 0, d.shape[0], idx)])


def _incidence(out_idx: np.ndarray, in_idx: np.ndarray, out_size: int,
               in_size: int) -> sp.csr_matrix:
    return sp.csr_matrix(
        (np.ones(out_idx.size, bool), (out_idx.reshape(-1), in_idx.reshape(-1))),
        shape=(out_size, in_size),
    )


class _Analysis:
    def __init__(self, n: int):
        self.n = n


    # -- values of constants (for index operands) -----------------------------------
    @staticmethod
    def _value(x: Any, vals: dict) -> Any:
        if isinstance(x, jex_core.Literal):
            return np.asarray(x.val)
        return vals.get(x)

    def run(self, jaxpr: Any, in_deps: list[Dep], in_vals: list[Any]) -> list[Dep]:
        deps: dict[Any, Dep] = {}
        vals: dict[Any, Any] = {}
        for v, d, val in zip(jaxpr.invars, in_deps, in_vals):
            deps[v] = d
            if val is not None:
                vals[v] = val
        for eqn in jaxpr.eqns:
            ins = [None if isinstance(x, jex_core.Literal) else deps.get(x) for x in eqn.invars]
            ivals = [self._value(x, vals) for x in eqn.invars]
            if all(d is None for d in ins):
                # no tangent flows through: fold small constants for later index lookups
                if all(v is not None for v in ivals) and all(
                    _size(o.aval) <= _MAX_EVAL and not jnp.issubdtype(o.aval.dtype, jnp.inexact)
                    for o in eqn.outvars
                ):
                    try:
                        for o, ov in zip(eqn.outvars, _evaluate(eqn, ivals)):
                            vals[o] = ov
                    except Exception:  # noqa: BLE001 - folding is an optimisation only
                        pass
                continue
            outs = self._eqn(eqn, ins, ivals)
            for o, d in zip(eqn.outvars, outs):
                deps[o] = d
        return [
            None if isinstance(v, jex_core.Literal) else deps.get(v) for v in jaxpr.outvars
        ]

    # -- one equation ----------------------------------------------------------------
    def _eqn(self, eqn: Any, ins: list[Dep], ivals: list[Any]) -> list[Dep]:
        name = eqn.primitive.name
        outs = eqn.outvars
        try:
            if name in _ELEMENTWISE:
                shape = tuple(outs[0].aval.shape)
                return [_union([_broadcast(d, tuple(x.aval.shape), shape)
                                for d, x in zip(ins, eqn.invars)], _size(outs[0].aval), self.n)]
            if name in _COPY_ONE or name in _COPY_ALL or name in (
                "pad", "gather", "dynamic_slice", "dynamic_update_slice", "split"
            ):
                res = self._copy(eqn, ins, ivals)
                if res is not None:
                    return res
            elif name in _REDUCE:
                return [self._reduce(eqn, ins[0])]
            elif name == "dot_general":
                return [self._dot(eqn, ins)]
            elif name == "optimization_barrier":  # identity on each operand
                return list(ins)
            elif name == "cond":
                return self._cond(eqn, ins, ivals)
            else:
                sub = self._subjaxpr(eqn)
                if sub is not None:
                    jaxpr, consts = sub
                    cvals = [np.asarray(c) if _is_concrete(c) else None for c in consts]
                    return self.run(jaxpr, [None] * len(consts) + ins, cvals + ivals)
        except Exception:  # noqa: BLE001 - anything unmodelled: the conservative answer
            pass
        return self._conservative(eqn, ins)

    def _conservative(self, eqn: Any, ins: list[Dep]) -> list[Dep]:
        present = [d for d in ins if d is not None]
        allin = _clean(sp.vstack(present).tocsr())
        return [_dense_dep(allin, _size(o.aval), self.n) for o in eqn.outvars]

    @staticmethod
    def _subjaxpr(eqn: Any) -> tuple[Any, list[Any]] | None:
        if eqn.primitive.name not in _CALLS:
            return None
        for key in ("jaxpr", "call_jaxpr", "fun_jaxpr"):
            j = eqn.params.get(key)
            if j is None:
                continue
            if isinstance(j, jex_core.ClosedJaxpr):
                jaxpr, consts = j.jaxpr, list(j.consts)
            elif isinstance(j, jex_core.Jaxpr):
                jaxpr, consts = j, []
            else:
                continue
            if len(jaxpr.invars) == len(eqn.invars) and len(jaxpr.outvars) == len(eqn.outvars):
                if consts and len(jaxpr.constvars) == len(consts):
                    return _inline_consts(jaxpr), consts
                return jaxpr, []
        return None

    def _cond(self, eqn: Any, ins: list[Dep], ivals: list[Any]) -> list[Dep]:
        outs: list[Dep] | None = None
        for br in eqn.params["branches"]:
            cvals = [np.asarray(c) if _is_concrete(c) else None for c in br.consts]
            jaxpr = _inline_consts(br.jaxpr) if br.consts else br.jaxpr
            r = self.run(jaxpr, [None] * len(br.consts) + ins[1:], cvals + ivals[1:])
            outs = r if outs is None else [
                _union([a, b], _size(o.aval), self.n) for a, b, o in zip(outs, r, eqn.outvars)
            ]
        return outs if outs is not None else [None] * len(eqn.outvars)

    def _copy(self, eqn: Any, ins: list[Dep], ivals: list[Any]) -> list[Dep] | None:
        """Primitives whose outputs are copies of input elements: evaluate them on the
        element indices (int64 iotas, −1 where a value is not copied from an operand)."""
        name = eqn.primitive.name
        data = {
            "gather": [0], "dynamic_slice": [0], "pad": [0, 1], "dynamic_update_slice": [0, 1],
        }.get(name, list(range(len(eqn.invars))))
        args, offset, stacked = [], 0, []
        for i, x in enumerate(eqn.invars):
            if i in data:
                size = _size(x.aval)
                args.append(np.arange(offset, offset + size, dtype=np.int32).reshape(
                    x.aval.shape))
                d = ins[i]
                stacked.append(d if d is not None else sp.csr_matrix((size, self.n), dtype=bool))
                offset += size
            else:
                if ivals[i] is None:
                    return None  # traced index: conservative
                args.append(ivals[i])
        if name == "gather":  # copies out of bounds read −1 (no operand element)
            params = dict(eqn.params)
            if "fill_value" in params:
                params["fill_value"] = -1
            outs = _bind(eqn, args, params)
        else:
            outs = _evaluate(eqn, args, cast=False)
        alldeps = _clean(sp.vstack(stacked).tocsr())
        return [_gather_rows(alldeps, np.asarray(o)) for o in outs]

    def _reduce(self, eqn: Any, d: sp.csr_matrix) -> sp.csr_matrix:
        shape = eqn.invars[0].aval.shape
        axes = tuple(eqn.params["axes"])
        keep = [a for a in range(len(shape)) if a not in axes]
        out_shape = tuple(shape[a] for a in keep)
        out_iota = np.arange(int(np.prod(out_shape, dtype=np.int64))).reshape(out_shape)
        exp = np.expand_dims(out_iota, axes) if axes else out_iota
        out_idx = np.broadcast_to(exp, shape)
        m = _incidence(out_idx, np.arange(out_idx.size), out_iota.size, out_idx.size)
        return _clean(m @ d)

    def _dot(self, eqn: Any, ins: list[Dep]) -> Dep:
        (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
        ls, rs = eqn.invars[0].aval.shape, eqn.invars[1].aval.shape
        lf = [a for a in range(len(ls)) if a not in lc and a not in lb]
        rf = [a for a in range(len(rs)) if a not in rc and a not in rb]
        bsz = int(np.prod([ls[a] for a in lb], dtype=np.int64))
        csz = int(np.prod([ls[a] for a in lc], dtype=np.int64))
        fl = int(np.prod([ls[a] for a in lf], dtype=np.int64))
        fr = int(np.prod([rs[a] for a in rf], dtype=np.int64))
        out_size = bsz * fl * fr
        out_idx = np.arange(out_size).reshape(bsz, fl, fr, 1)
        parts = []
        if ins[0] is not None:
            li = np.arange(_size(eqn.invars[0].aval)).reshape(ls)
            li = np.transpose(li, (*lb, *lf, *lc)).reshape(bsz, fl, 1, csz)
            o, i = np.broadcast_arrays(out_idx, li)
            parts.append(_incidence(o, i, out_size, li.size) @ ins[0])
        if ins[1] is not None:
            ri = np.arange(_size(eqn.invars[1].aval)).reshape(rs)
            ri = np.transpose(ri, (*rb, *rf, *rc)).reshape(bsz, 1, fr, csz)
            o, i = np.broadcast_arrays(out_idx, ri)
            parts.append(_incidence(o, i, out_size, ri.size) @ ins[1])
        return _union(parts, out_size, self.n)


def _bind(eqn: Any, args: list[Any], params: dict[str, Any]) -> list[np.ndarray]:
    with jax.ensure_compile_time_eval():
        out = eqn.primitive.bind(*[jnp.asarray(a) for a in args], **params)
    return [np.asarray(o) for o in (out if eqn.primitive.multiple_results else [out])]


def _evaluate(eqn: Any, args: list[Any], *, cast: bool = True) -> list[np.ndarray]:
    """Outputs of ``eqn`` on concrete ``args``: NumPy where :mod:`._host_eval` has a rule
    (``cast``: see :func:`host_eval`), else the primitive bound eagerly (one small XLA
    compilation)."""
    try:
        return host_eval(eqn, args, cast=cast)
    except UnsupportedPrimitiveError:
        return _bind(eqn, args, eqn.params)


def _is_concrete(x: Any) -> bool:
    return isinstance(x, (np.ndarray, np.generic)) or (
        isinstance(x, jax.Array) and not isinstance(x, core.Tracer)
    )


def _inline_consts(jaxpr: Any) -> Any:
    """A jaxpr whose constvars become leading invars (so consts are passed as inputs)."""
    return jaxpr.replace(invars=list(jaxpr.constvars) + list(jaxpr.invars), constvars=[])


_CACHE: OrderedDict[tuple[Any, ...], sp.csr_matrix] = OrderedDict()
CACHE_SIZE = 32


def _fingerprint(c: Any) -> str:
    if not _is_concrete(c):
        return f"traced:{getattr(c, 'shape', ())}:{getattr(c, 'dtype', '')}"
    a = np.asarray(c)
    return f"{a.dtype}{a.shape}" + hashlib.sha1(np.ascontiguousarray(a).tobytes()).hexdigest()


def _nested_consts(jaxpr: Any) -> list[Any]:
    """The constants of every sub-program of ``jaxpr`` (a nested ``jit``'s closed jaxpr
    keeps the arrays its function closes over), in order: the printed program names them
    but does not show their values, on which the pattern may depend (an index array)."""
    out: list[Any] = []

    def visit(p: Any) -> None:
        if isinstance(p, tuple | list):
            for q in p:
                visit(q)
            return
        if isinstance(p, jex_core.ClosedJaxpr):
            out.extend(p.consts)
            p = p.jaxpr  # p itself from jax 0.11 (ClosedJaxpr is an alias of Jaxpr there)
        if isinstance(p, jex_core.Jaxpr):
            for eqn in p.eqns:
                for v in eqn.params.values():
                    visit(v)

    visit(jaxpr)
    return out


def jacobian_pattern(f: Callable[[jax.Array], jax.Array], x: jax.Array
                     ) -> tuple[tuple[Any, ...], sp.csr_matrix]:
    """``(key, P)``: the boolean (m, n) structural pattern P of the Jacobian of
    ``f: (n,) -> (m,)`` at any point (``x`` gives only shape and dtype; see the module
    docstring) and a key identifying the analysed program (equal keys, equal patterns).
    Patterns are cached by that program (its jaxpr and the values of its constants, those
    of nested sub-programs included)."""
    x = jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x))
    n = int(x.shape[0])

    def tangent(e: jax.Array, t: jax.Array) -> jax.Array:
        return jax.jvp(f, (e,), (t,))[1]

    closed = jax.make_jaxpr(tangent)(x, x)
    if len(closed.jaxpr.outvars) != 1 or len(closed.jaxpr.outvars[0].aval.shape) != 1:
        raise ValueError("jacobian_pattern: f must map an (n,) vector to an (m,) vector")
    consts = list(closed.consts)
    key = (str(closed.jaxpr),
           tuple(_fingerprint(c) for c in consts + _nested_consts(closed.jaxpr)))
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return key, _CACHE[key]
    jaxpr = _inline_consts(closed.jaxpr)
    cvals = [np.asarray(c) if _is_concrete(c) else None for c in consts]
    eye = sp.identity(n, dtype=bool, format="csr")
    (out,) = _Analysis(n).run(jaxpr, [None] * len(consts) + [None, eye],
                              cvals + [None, None])
    m = _size(closed.jaxpr.outvars[0].aval)
    pattern = sp.csr_matrix((m, n), dtype=bool) if out is None else _clean(out)
    _CACHE[key] = pattern
    if len(_CACHE) > CACHE_SIZE:
        _CACHE.popitem(last=False)
    return key, pattern


__all__ = ["jacobian_pattern"]
