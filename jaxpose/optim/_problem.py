"""The least-squares problem: residual function, weights, kernels and linearisation.

Conventions
-----------
* ``residual_fn(params, args)`` returns a pytree of arrays. Each leaf of shape
  ``(*batch, d)`` holds ``prod(batch)`` residual *blocks* of dimension d (the last axis,
  as in PyPose); a 0-d leaf is one block of dimension 1. Kernels act on each block's
  squared whitened norm.
* ``weights``: per-block information matrices W (symmetric positive definite). ``None``,
  one array used for every residual leaf, or a pytree matching the residual with an
  array or ``None`` per leaf. A weight for a leaf of shape ``(*batch, d)`` is a scalar
  (W = w·I) or has shape ``(..., d, d)`` broadcastable to ``(*batch, d, d)``.
* cost = ``0.5 · Σ_blocks ρ(rᵀ W r)``, ρ(s) = s without a kernel.
* Whitening: W = L Lᵀ (Cholesky), e = Lᵀ r, so ‖e‖² = rᵀ W r; the Jacobian rows are
  whitened the same way, then corrected for the kernel. Cost, step and gain ratio all
  use these same whitened quantities, so weights act consistently everywhere.
* Flattening: residual rows follow ``jax.flatten_util.ravel_pytree`` of the residual
  pytree; tangent columns follow ``manifold.flat_tangent(params)``. Group
  leaves contribute ``tangent_dim`` columns (right perturbation X·Exp(δ)), never storage
  (quaternion) columns. A user ``jacobian(params, args)`` must return this (m, n) matrix.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from .. import _small_linalg as small_linalg
from ..lie import manifold
from ._colouring import Pattern, SparseJacobian, compressed_jacobian, make_pattern
from ._correctors import Corrector, FastTriggs
from ._kernels import Kernel
from ._sparsity import jacobian_pattern

Array = jax.Array
PyTree = Any


# jacobian="auto" colours the Jacobian when the tangent has at least this many entries and
# the colouring needs at most this fraction of min(m, n) JVPs
AUTO_MIN_TANGENT = 48
AUTO_MAX_COLOUR_FRACTION = 0.25
_PATTERNS: dict[tuple[Any, ...], Pattern] = {}


class LinearizedResidual(NamedTuple):
    """The dense problem linearised at one point (:meth:`Problem.linearize`): whitened,
    kernel-corrected residual ẽ (m,) and Jacobian J̃ (m, n) plus the cost.

    ``jac`` is a :class:`~jaxpose.optim._colouring.SparseJacobian` on the coloured path of
    :meth:`Problem.linearize_structured`; :meth:`Problem.linearize` always gives (m, n)."""

    res: Array
    jac: Array | SparseJacobian
    cost: Array


def _block_of_row(leaves: list[Any]) -> np.ndarray:
    """Residual block index of every flattened residual row (m,)."""
    parts, offset = [], 0
    for leaf in leaves:
        d, batch = _block_dim(tuple(leaf.shape))
        nb = int(np.prod(batch))
        parts.append(offset + np.repeat(np.arange(nb), d))
        offset += nb
    return np.concatenate(parts) if parts else np.zeros((0,), np.int64)


def _is_kernel_leaf(x: Any) -> bool:
    return x is None or isinstance(x, Kernel)


def _is_weight_leaf(x: Any) -> bool:
    return x is None or eqx.is_array_like(x)


def _block_dim(shape: tuple[int, ...]) -> tuple[int, tuple[int, ...]]:
    if len(shape) == 0:
        return 1, ()
    return int(shape[-1]), tuple(shape[:-1])


class _Resolved:
    """:meth:`Problem.jacobian_mode`'s answer kept by :meth:`Problem.resolve` (a static
    field: hashed and compared by identity)."""

    __slots__ = ("mode", "pattern")

    def __init__(self, mode: str, pattern: Pattern | None):
        self.mode, self.pattern = mode, pattern


class Problem(eqx.Module):
    """A residual function plus everything that shapes its cost (see module docstring).

    ``jacobian``: ``"auto"`` (coloured when the Jacobian is sparse enough, else jacfwd
    when the tangent is no larger than the residual, jacrev otherwise), ``"fwd"``,
    ``"rev"``, ``"sparse"`` (always coloured: structural sparsity from the JVP program,
    one JVP per colour; see :mod:`jaxpose.optim._colouring`), or a callable
    ``(params, args) -> (m, n)``.
    ``corrector`` defaults to :class:`FastTriggs` when a kernel is given."""

    residual_fn: Callable[[PyTree, PyTree], PyTree]
    weights: PyTree = None
    kernel: PyTree = None
    corrector: Corrector | None = None
    jacobian: str | Callable[..., Array] = eqx.field(default="auto")
    # set by resolve(): the Jacobian mode for one set of shapes (identity-hashed)
    _resolved: _Resolved | None = eqx.field(static=True, default=None, repr=False)

    def __check_init__(self) -> None:
        if not callable(self.residual_fn):
            raise TypeError(
                f"residual_fn: expected a callable residual_fn(params, args), got "
                f"{type(self.residual_fn).__name__}"
            )
        if not (callable(self.jacobian) or self.jacobian in ("auto", "fwd", "rev", "sparse")):
            raise ValueError(
                f"jacobian={self.jacobian!r}: expected 'auto', 'fwd', 'rev', 'sparse' or a "
                f"callable jacobian(params, args) -> (m, n) array"
            )
        if self.corrector is not None and not isinstance(self.corrector, Corrector):
            raise TypeError(
                f"corrector: expected a jaxpose.optim Corrector (FastTriggs, Triggs) or None, "
                f"got {type(self.corrector).__name__}"
            )

    # ------------------------------------------------------------------------------
    # trace-time validation
    # ------------------------------------------------------------------------------
    def check(self, params: PyTree, args: PyTree) -> None:
        """Validate weights, kernels and a user Jacobian against the residual's shapes."""
        try:
            out = jax.eval_shape(self.residual_fn, params, args)
        except Exception as err:  # noqa: BLE001 - re-raise with the argument named
            raise type(err)(f"residual_fn(params, args) failed to trace: {err}") from err
        leaves, treedef = jax.tree.flatten(out)
        if not leaves:
            raise ValueError("residual_fn: returned no arrays (an empty pytree)")
        for leaf in leaves:
            if not jnp.issubdtype(leaf.dtype, jnp.floating):
                raise TypeError(f"residual_fn: returned a {leaf.dtype} array; expected floats")
        sizes = [int(np.prod(leaf.shape)) for leaf in leaves]
        if sum(sizes) == 0:
            raise ValueError("residual_fn: returned 0 residuals; expected at least one")
        if 0 in sizes:
            i = sizes.index(0)
            raise ValueError(
                f"residual_fn: residual leaf {i} has shape {tuple(leaves[i].shape)} (0 "
                f"residuals); expected at least one in every leaf (leave out empty leaves)"
            )
        self._weight_leaves(leaves, treedef)
        self._kernel_leaves(leaves, treedef)
        if callable(self.jacobian):
            m = sum(int(np.prod(leaf.shape)) for leaf in leaves)
            n = manifold.tangent_size(params)
            j = jax.eval_shape(self.jacobian, params, args)
            if not hasattr(j, "shape") or tuple(j.shape) != (m, n):
                got = getattr(j, "shape", type(j).__name__)
                raise ValueError(
                    f"jacobian(params, args): expected a dense tangent-space Jacobian of shape "
                    f"({m}, {n}) (residual size, tangent size), got {got}"
                )

    def _with_checked_kernels(self) -> Problem:
        """This problem with its kernels' traced parameters (``Huber(d)`` with ``d`` traced)
        checked at run time (``eqx.error_if``, once per solve); known values were checked
        when the kernels were made."""
        if self.kernel is None:
            return self
        kernel = jax.tree.map(lambda k: None if k is None else k._checked(), self.kernel,
                              is_leaf=_is_kernel_leaf)
        return dataclasses.replace(self, kernel=kernel)

    def _weight_leaves(self, leaves: list[Any], treedef: Any) -> list[Any]:
        if self.weights is None:
            return [None] * len(leaves)
        if eqx.is_array_like(self.weights):
            wl = [self.weights] * len(leaves)
        else:
            wl, wdef = jax.tree.flatten(self.weights, is_leaf=_is_weight_leaf)
            if wdef != treedef:
                raise ValueError(
                    f"weights: expected None, one array, or a pytree matching the residual "
                    f"structure {treedef}; got structure {wdef}"
                )
        for i, (w, leaf) in enumerate(zip(wl, leaves)):
            if w is None:
                continue
            wshape = tuple(jnp.shape(w))
            d, batch = _block_dim(tuple(leaf.shape))
            ok = len(wshape) == 0
            if len(wshape) >= 2 and wshape[-2:] == (d, d):
                try:
                    ok = tuple(np.broadcast_shapes(wshape[:-2], batch)) == batch
                except ValueError:
                    ok = False
            if not ok:
                raise ValueError(
                    f"weights: residual leaf {i} has shape {tuple(leaf.shape)} (blocks of "
                    f"dimension {d}); expected a scalar or an information matrix of shape "
                    f"(..., {d}, {d}) broadcastable to {(*batch, d, d)}, got shape {wshape}"
                )
        return wl

    def _kernel_leaves(self, leaves: list[Any], treedef: Any) -> list[Kernel | None]:
        if self.kernel is None:
            return [None] * len(leaves)
        if isinstance(self.kernel, Kernel):
            return [self.kernel] * len(leaves)
        kl, kdef = jax.tree.flatten(self.kernel, is_leaf=_is_kernel_leaf)
        if kdef != treedef or not all(_is_kernel_leaf(k) for k in kl):
            raise ValueError(
                f"kernel: expected a Kernel, None, or a pytree of Kernel/None matching the "
                f"residual structure {treedef}; got {self.kernel!r}"
            )
        return kl

    # ------------------------------------------------------------------------------
    # evaluation
    # ------------------------------------------------------------------------------
    def _blocks(self, out: PyTree, jac: Array | None) -> LinearizedResidual:
        """Whiten, robustify and flatten residual leaves (and Jacobian rows if given)."""
        leaves, treedef = jax.tree.flatten(out)
        weights = self._weight_leaves(leaves, treedef)
        kernels = self._kernel_leaves(leaves, treedef)
        corrector = self.corrector if self.corrector is not None else FastTriggs()
        dtype = jnp.result_type(*leaves)
        res_parts, jac_parts, cost = [], [], jnp.zeros((), dtype)
        offset = 0
        for leaf, w, k in zip(leaves, weights, kernels):
            d, batch = _block_dim(tuple(leaf.shape))
            nb = int(np.prod(batch))
            size = nb * d
            e = jnp.reshape(leaf, (nb, d)).astype(dtype)
            jb = None if jac is None else jnp.reshape(jac[offset : offset + size], (nb, d, -1))
            offset += size
            if w is not None:
                w = jnp.asarray(w, dtype)
                if w.ndim == 0:
                    lw = jnp.sqrt(w)
                    lw = eqx.error_if(
                        lw, ~jnp.isfinite(lw) | (w <= 0), "weights: a scalar weight is not positive"
                    )
                    e = lw * e
                    jb = None if jb is None else lw * jb
                else:
                    wb = jnp.reshape(jnp.broadcast_to(w, (*batch, d, d)), (nb, d, d))
                    chol = small_linalg.cholesky(wb)
                    chol = eqx.error_if(
                        chol,
                        ~jnp.all(jnp.isfinite(chol)),
                        "weights: an information matrix is not symmetric positive definite",
                    )
                    e = jnp.einsum("bij,bi->bj", chol, e)  # e = Lᵀ r
                    jb = None if jb is None else jnp.einsum("bij,bin->bjn", chol, jb)
            s = jnp.sum(e * e, axis=-1)
            if k is None:
                cost = cost + 0.5 * jnp.sum(s)
            else:
                k = k._in_dtype(s.dtype)
                cost = cost + 0.5 * jnp.sum(k(s))
                if jb is not None:
                    e, jb = corrector(k, e, jb)
            res_parts.append(jnp.reshape(e, (-1,)))
            if jb is not None:
                jac_parts.append(jnp.reshape(jb, (size, -1)))
        res = jnp.concatenate(res_parts)
        jac_out = None if jac is None else jnp.concatenate(jac_parts, 0)
        return LinearizedResidual(res, jac_out, cost)

    def cost(self, params: PyTree, args: PyTree) -> Array:
        """``0.5 · Σ ρ(rᵀ W r)`` at ``params`` (a scalar)."""
        return self._blocks(self.residual_fn(params, args), None).cost

    def _flat_fn(self, params: PyTree, args: PyTree, holder: list[Any] | None = None
                 ) -> tuple[Array, Callable[[Array], Array]]:
        """(zeros (n,), g): g(ε) is the flattened residual at ``params ⊕ ε`` (to first
        order in ε: g is only differentiated once, at ε = 0); each call appends the
        residual's unravel function to ``holder`` when one is given."""
        flat0, unravel = manifold.flat_tangent(params)

        def g(eps: Array) -> Array:
            out = self.residual_fn(manifold.retract_linear(params, unravel(eps)), args)
            flat, unravel_out = ravel_pytree(out)
            if holder is not None:
                holder.append(unravel_out)
            return flat

        return flat0, g

    def pattern(self, params: PyTree, args: PyTree) -> Pattern:
        """The coloured structural Jacobian pattern at ``params``' shapes (cached by the
        residual program and the residual's block layout)."""
        flat0, g = self._flat_fn(params, args)
        key, jp = jacobian_pattern(g, flat0)
        leaves = jax.tree.leaves(jax.eval_shape(self.residual_fn, params, args))
        shapes = tuple(tuple(leaf.shape) for leaf in leaves)
        if (key, shapes) not in _PATTERNS:
            if len(_PATTERNS) > 64:
                _PATTERNS.clear()
            _PATTERNS[(key, shapes)] = make_pattern(jp, _block_of_row(leaves))
        return _PATTERNS[(key, shapes)]

    def _resolve(self, params: PyTree, args: PyTree) -> Problem:
        """This problem with :meth:`jacobian_mode` decided once for the shapes of
        ``params`` and ``args`` (the sparsity analysis traces the residual program;
        a solve linearises many times at the same shapes). Use it only with those shapes and
        this residual function: least_squares resolves the problem it is given (private:
        a resolved problem whose residual_fn is replaced keeps the old pattern)."""
        mode, pattern = self.jacobian_mode(params, args)
        return dataclasses.replace(self, _resolved=_Resolved(mode, pattern))

    def jacobian_mode(self, params: PyTree, args: PyTree) -> tuple[str, Pattern | None]:
        """How :meth:`linearize` differentiates: ``("user" | "fwd" | "rev", None)`` or
        ``("sparse", pattern)``."""
        if self._resolved is not None:
            return self._resolved.mode, self._resolved.pattern
        if callable(self.jacobian):
            return "user", None
        if self.jacobian == "sparse":
            return "sparse", self.pattern(params, args)
        if self.jacobian != "auto":
            return self.jacobian, None
        n = manifold.tangent_size(params)
        out_shape = jax.eval_shape(self.residual_fn, params, args)
        m = sum(int(np.prod(leaf.shape)) for leaf in jax.tree.leaves(out_shape))
        if n >= AUTO_MIN_TANGENT:
            try:
                pat = self.pattern(params, args)
            except Exception:  # noqa: BLE001 - an unanalysable program: the dense path
                pat = None
            if pat is not None and pat.num_colours <= AUTO_MAX_COLOUR_FRACTION * min(m, n):
                return "sparse", pat
        return ("fwd" if n <= m else "rev"), None

    def linearize(self, params: PyTree, args: PyTree) -> LinearizedResidual:
        """Residual, tangent-space Jacobian (whitened, corrected; dense (m, n)) and cost."""
        lin = self.linearize_structured(params, args)
        if isinstance(lin.jac, SparseJacobian):
            return LinearizedResidual(lin.res, lin.jac.dense(), lin.cost)
        return lin

    def linearize_structured(self, params: PyTree, args: PyTree) -> LinearizedResidual:
        """:meth:`linearize`, with the Jacobian as a :class:`SparseJacobian` (compressed
        values (m, c)) on the coloured path."""
        mode, pat = self.jacobian_mode(params, args)
        if mode == "user":
            out = self.residual_fn(params, args)
            jac = jnp.asarray(self.jacobian(params, args))
            return self._blocks(out, jac)
        holder: list[Any] = []
        flat0, f = self._flat_fn(params, args, holder)
        if mode == "sparse":
            flat_out, comp = compressed_jacobian(f, flat0, pat)
            lin = self._blocks(holder[-1](flat_out), comp)
            return LinearizedResidual(lin.res, SparseJacobian(lin.jac, pat), lin.cost)

        def f_aux(eps: Array) -> tuple[Array, Array]:
            flat = f(eps)
            return flat, flat

        jac_fn = jax.jacfwd if mode == "fwd" else jax.jacrev
        jac, flat_out = jac_fn(f_aux, has_aux=True)(flat0)
        out = holder[-1](flat_out)
        return self._blocks(out, jac)


def as_problem(residual_fn: Callable[..., PyTree] | Problem, **kwargs: Any) -> Problem:
    """Wrap a residual function (or pass a :class:`Problem` through unchanged)."""
    if isinstance(residual_fn, Problem):
        extra = {k: v for k, v in kwargs.items() if v is not None and v != "auto"}
        if extra:
            raise ValueError(
                f"least_squares: got a Problem together with {sorted(extra)}; set them on "
                f"the Problem instead"
            )
        return residual_fn
    return Problem(residual_fn, **kwargs)


__all__ = ["Problem", "LinearizedResidual", "as_problem"]
