"""Tangent-space calculus over pytrees that mix Lie groups and plain arrays.

Conventions
-----------
* Retraction (right perturbation): ``X ⊕ δ = X · Exp(δ)`` for every :class:`LieGroup`
  leaf, ``a ⊕ δ = a + δ`` for array leaves. ``rminus`` is its inverse:
  ``Y ⊖ X = Log(X⁻¹ · Y)``, so ``X ⊕ (Y ⊖ X) = Y``.
* A *tangent pytree* has the structure of the parameters with every group leaf
  replaced by a plain array of shape ``(*batch, tangent_dim)``; array leaves keep
  their shape. It is an ordinary pytree of arrays, so optax, ``ravel_pytree`` and
  ``jax.tree`` functions apply to it directly.
* Gradients and Jacobians are taken with respect to δ at δ = 0, i.e. in the right
  (body) tangent space of each group element. Euclidean gradients of the stored
  quaternion are never exposed.

:func:`optax_on_manifold` runs any optax optimizer on such parameters: updates are
computed in the tangent space and applied through the retraction (moments are kept in
the local frame without transport, as in jaxlie / Theseus).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from ._base import LieGroup

PyTree = Any


def is_group(x: Any) -> bool:
    """True for Lie group elements (treated as leaves by this module)."""
    return isinstance(x, LieGroup)


def _map(fn: Callable[..., Any], tree: PyTree, *rest: PyTree) -> PyTree:
    return jax.tree.map(fn, tree, *rest, is_leaf=is_group)


def zero_tangent(params: PyTree) -> PyTree:
    """Zero tangent pytree for ``params`` (groups → zeros (*batch, tangent_dim))."""

    def zero(x: Any) -> Any:
        if is_group(x):
            return jnp.zeros((*x.shape, x.tangent_dim), x.dtype)
        return jnp.zeros_like(x)

    return _map(zero, params)


def flat_tangent(params: PyTree) -> tuple[jax.Array, Callable[[jax.Array], PyTree]]:
    """(zeros (n,), unravel): the flat tangent layout of ``params`` (``ravel_pytree`` of
    :func:`zero_tangent`, n = :func:`tangent_size`); ``unravel`` maps (n,) to a tangent
    pytree for :func:`retract`."""
    return ravel_pytree(zero_tangent(params))


def _retract_by(method: str, params: PyTree, delta: PyTree) -> PyTree:
    """``params ⊕ delta`` with the group leaves' ``method``; a + δ on array leaves."""

    def plus(x: Any, d: Any) -> Any:
        if is_group(x):
            return getattr(x, method)(d)
        return x + d

    return _map(plus, params, delta)


def retract(params: PyTree, delta: PyTree) -> PyTree:
    """``params ⊕ delta``: X·Exp(δ) on group leaves, a + δ on array leaves."""
    return _retract_by("retract", params, delta)


def retract_linear(params: PyTree, delta: PyTree) -> PyTree:
    """:func:`retract` to first order in ``delta``: ``X·E(δ)`` on group leaves
    (:meth:`~jaxpose.lie.LieGroup.retract_linear`), a + δ on array leaves. Same value and
    first derivative at δ = 0, so use it for Jacobians taken at δ = 0 (exact, and
    exactly differentiable in everything else) — never for a step or a second
    derivative in δ."""
    return _retract_by("retract_linear", params, delta)


def retract_quadratic(params: PyTree, delta: PyTree) -> PyTree:
    """:func:`retract` to second order in ``delta`` (``X·E₂(δ)``,
    :meth:`~jaxpose.lie.LieGroup.retract_quadratic`): exact gradients and Hessians in δ
    at δ = 0; never for a step or third derivatives in δ."""
    return _retract_by("retract_quadratic", params, delta)


def rminus(a: PyTree, b: PyTree) -> PyTree:
    """``a ⊖ b``: Log(b⁻¹·a) on group leaves, a − b on array leaves."""

    def minus(x: Any, y: Any) -> Any:
        if is_group(x):
            return x.rminus(y)
        return x - y

    return _map(minus, a, b)


def normalize_all(params: PyTree) -> PyTree:
    """Re-project every group leaf onto its manifold (e.g. renormalise quaternions)."""
    return _map(lambda x: x.normalize() if is_group(x) else x, params)


def tangent_size(params: PyTree) -> int:
    """Total number of tangent-space coordinates in ``params``."""
    leaves = jax.tree.leaves(zero_tangent(params))
    return int(sum(leaf.size for leaf in leaves))


def _lift(fun: Callable[..., Any], args: tuple[Any, ...], argnums: int | Sequence[int]):
    """Wrap ``fun`` as a function of tangent deltas at the positions ``argnums``."""
    nums = (argnums,) if isinstance(argnums, int) else tuple(argnums)

    def lifted(*deltas: PyTree) -> Any:
        new_args = list(args)
        for i, d in zip(nums, deltas, strict=True):
            new_args[i] = retract(args[i], d)
        return fun(*new_args)

    zeros = tuple(zero_tangent(args[i]) for i in nums)
    # an int argnums gives jax an int too, so results are not wrapped in a 1-tuple
    inner = 0 if isinstance(argnums, int) else tuple(range(len(nums)))
    return lifted, zeros, inner


def grad(fun: Callable[..., Any], argnums: int | Sequence[int] = 0, has_aux: bool = False):
    """Like :func:`jax.grad`, with respect to tangent deltas of the chosen arguments."""

    def g(*args: Any) -> Any:
        lifted, zeros, inner = _lift(fun, args, argnums)
        return jax.grad(lifted, argnums=inner, has_aux=has_aux)(*zeros)

    return g


def value_and_grad(
    fun: Callable[..., Any], argnums: int | Sequence[int] = 0, has_aux: bool = False
):
    """Like :func:`jax.value_and_grad`, with tangent-space gradients."""

    def vg(*args: Any) -> Any:
        lifted, zeros, inner = _lift(fun, args, argnums)
        return jax.value_and_grad(lifted, argnums=inner, has_aux=has_aux)(*zeros)

    return vg


def jacobian(
    fun: Callable[..., Any], argnums: int | Sequence[int] = 0, mode: str = "auto",
    has_aux: bool = False,
):
    """Tangent-space Jacobian of ``fun``: d fun(X ⊕ δ) / dδ at δ = 0.

    ``mode`` is ``"fwd"`` (jacfwd), ``"rev"`` (jacrev) or ``"auto"`` (forward when the
    tangent is no larger than the output, reverse otherwise). The output leaves have
    shape ``(*out_shape, *tangent_leaf_shape)`` as with :func:`jax.jacobian`."""
    if mode not in ("auto", "fwd", "rev"):
        raise ValueError(f"jacobian(mode={mode!r}): expected 'auto', 'fwd' or 'rev'")

    def jac(*args: Any) -> Any:
        lifted, zeros, inner = _lift(fun, args, argnums)
        m = mode
        if m == "auto":
            n_in = sum(leaf.size for leaf in jax.tree.leaves(zeros))
            out_shape = jax.eval_shape(lifted, *zeros)
            if has_aux:
                out_shape = out_shape[0]
            n_out = sum(_prod(s.shape) for s in jax.tree.leaves(out_shape))
            m = "fwd" if n_in <= n_out else "rev"
        jf = jax.jacfwd if m == "fwd" else jax.jacrev
        return jf(lifted, argnums=inner, has_aux=has_aux)(*zeros)

    return jac


def _prod(shape: Sequence[int]) -> int:
    out = 1
    for s in shape:
        out *= int(s)
    return out


# ----------------------------------------------------------------------------------
# optax adapter
# ----------------------------------------------------------------------------------
class ManifoldOptimizer(NamedTuple):
    """An optax optimizer lifted to pytrees with Lie group leaves.

    ``init(params)`` → state; ``update(tangent_grads, state, params)`` → (tangent
    updates, state); ``apply_updates(params, updates)`` → params ⊕ updates. The tangent
    gradients come from :func:`grad` / :func:`value_and_grad`."""

    init: Callable[[PyTree], Any]
    update: Callable[..., tuple[PyTree, Any]]

    @staticmethod
    def apply_updates(params: PyTree, updates: PyTree) -> PyTree:
        """``params ⊕ updates`` (:func:`retract`): replaces ``optax.apply_updates``."""
        return retract(params, updates)


def optax_on_manifold(optimizer: Any) -> ManifoldOptimizer:
    """Wrap an ``optax.GradientTransformation`` so it optimises manifold parameters.

    Example::

        opt = optax_on_manifold(optax.adam(1e-2))
        state = opt.init(params)
        loss, g = manifold.value_and_grad(loss_fn)(params)
        updates, state = opt.update(g, state, params)
        params = opt.apply_updates(params, updates)
    """
    if not (hasattr(optimizer, "init") and hasattr(optimizer, "update")):
        raise TypeError(
            f"optax_on_manifold(optimizer): expected an optax.GradientTransformation, "
            f"got {type(optimizer).__name__}"
        )

    def init(params: PyTree) -> Any:
        return optimizer.init(zero_tangent(params))

    def update(grads: PyTree, state: Any, params: PyTree | None = None) -> tuple[PyTree, Any]:
        # Tangent-space optimizers see a zero "position" (the delta around params).
        tangent_params = None if params is None else zero_tangent(params)
        return optimizer.update(grads, state, tangent_params)

    return ManifoldOptimizer(init=init, update=update)
