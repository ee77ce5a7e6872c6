"""Fixed-lag smoothing over a window of the last ``K`` states.

The smoother holds the last ``K`` states of a stream in fixed-shape arrays (a shift
register: slot 0 is the oldest, slot ``K − 1`` the newest) together with the data of the
factors attached to them and a Gaussian prior on the window (the marginalised past).
Each :meth:`FixedLagSmoother.update`:

1. marginalises the oldest state, if the window is full: the factors touching slot 0
   (its unary factors, the motion factor to slot 1, loop factors ending in slot 0) and
   the current prior, linearised at the linearisation point (below) at the end of the
   previous update, and slot 0 is eliminated (Schur complement). The result is the new
   prior, stored as information ``H_p`` (n, n) and gradient ``g_p`` (n,) in the tangent
   chart at a linearisation point ``x̄`` (the linearisation point at marginalisation
   time): ``cost_p(x) = g_pᵀδ + ½δᵀH_pδ`` with ``δ = x ⊖ x̄`` per slot (``Log(x̄⁻¹x)``
   for groups). Those factors are dropped.
2. shifts the window by one slot and appends the new state (initial guess) and the
   step's factor data (a motion factor to the previous state, unary factors, up to
   ``M`` loop factors to older states still in the window; loop factors whose other end
   was marginalised are dropped, as in GTSAM, whose fixed-lag smoothers remove the
   factors of marginalised variables);
3. solves the window by Gauss–Newton until the largest change of the estimate (tangent
   components) is below ``tol``: without loop factors the system is block tridiagonal
   and is eliminated oldest slot first in ``O(K·d³)`` (:meth:`_eliminate`, ``d`` the
   tangent size of one state); with them it is dense (``n = K·d``, Cholesky). The
   smoother keeps the linearisation its last step was computed from (a chain's
   elimination, else the dense systems) and that point, ``lin``: the next
   marginalisation and :meth:`FixedLagSmoother.marginal_covariances` read it, so an
   update's program linearises the factors at one place (three before: 2.5x the
   StableHLO operations for the IMU + GPS smoother with covariances). At convergence
   the estimate is ``lin ⊕`` a last step below ``tol``, as in iSAM2, whose linearisation
   point also trails its estimate.

Incremental updates (``relinearize_threshold`` set; chains with first-estimate
Jacobians only). The smoother keeps the oldest-first elimination of the window at its
linearisation point ``lin`` (as every chain does): the message into every slot (the
information the older slots and the prior pass on) and the back-substitution
``Δ_s = a_s + M_s·Δ_{s+1}``. Eliminating slot 0 leaves exactly the message into
slot 1, so marginalisation takes that message as the new prior, at no cost; a new
state only needs its own factors linearised and the last two slots eliminated
(``O(d³)``), then one back-substitution (``O(K·d²)``) gives the estimate ``lin ⊕ Δ``.
The non-frozen states whose step ``Δ`` exceeds the threshold (largest tangent
component; or is not finite) are re-linearised at their estimate and the window is
eliminated again from the oldest of them (``O((K − j)·d³)``; iSAM2 re-linearises
lazily the same way). ``iterations`` is then 1, else 0. With ``relinearize_skip =
n > 1`` the threshold is checked only at every n-th update (iSAM2's
``relinearizeSkip``, default 10 there); a step that is not finite re-linearises at any
update.

The prior's linearisation point ``x̄`` never moves while the prior exists. With
``first_estimate=True`` (default; GTSAM's ``BatchFixedLagSmoother``, whose
``enforceConsistency`` is on by default) the states in the prior are *first-estimate*
states: every factor touching them is linearised at ``x̄`` (not at the current estimate),
so all information about them is expressed at one point and the system stays
consistent (no spurious information from re-linearisation). Their estimate is
``x̄ ⊕ Δ`` with Δ from the linearised system; the other states are re-linearised at each
iteration. With ``first_estimate=False`` every factor is re-linearised at the current
estimate and the prior is evaluated there through the chart ``δ = x ⊖ x̄`` (its Jacobian
``Jr⁻¹(δ)``, or the identity with ``exact_prior_jacobian=False`` as GTSAM's
``LinearContainerFactor``); the next marginalisation re-anchors the prior at the current
estimate.

States are pytrees mixing Lie groups and arrays (e.g. ``{"pose": SE3, "vel": (3,),
"bias": (6,)}``); tangent vectors of one state are ``ravel_pytree`` of its tangent pytree
(dict keys in sorted order, groups in their tangent layout, e.g. SE3 ``[ρ, φ]``).
"""

from __future__ import annotations

import functools
import math
import numbers
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax.flatten_util import ravel_pytree

from .._checks import check_count
from .._dtypes import keep_dtypes
from .._forward_only import forward_mode_only
from .._precision import full_precision
from ..lie import manifold
from ..lie._base import runtime_check, small_matmul
from ..results import Results

Array = jax.Array
PyTree = Any
_REVERSE_MODE = (
    "FixedLagSmoother.update: reverse-mode derivatives (grad, jacrev, vjp) cannot pass "
    "through its Gauss-Newton lax.while_loop; use forward mode (jax.jvp, jax.jacfwd), which "
    "differentiates the iterates.")


# jitted: used eagerly (construction, accessors such as ``newest``), op by op they
# compiled one tiny XLA program per leaf, shape and index (~100 in the smoother notebook)
@functools.partial(jax.jit, static_argnums=1)
def _stack(x: PyTree, k: int) -> PyTree:
    return jax.tree.map(lambda a: jnp.broadcast_to(jnp.asarray(a)[None], (k, *jnp.shape(a))), x)


@jax.jit
def _take(x: PyTree, i: Any) -> PyTree:
    return jax.tree.map(lambda a: a[i], x)


def _shift_in(x: PyTree, new: PyTree) -> PyTree:
    """Drop slot 0, append ``new`` as the last slot."""
    return jax.tree.map(
        lambda a, b: jnp.concatenate([a[1:], jnp.asarray(b, a.dtype)[None]]), x, new
    )


def _where(c: Array, a: PyTree, b: PyTree) -> PyTree:
    """Select per slot (``c`` of shape (K,) or ()) between stacked pytrees."""

    def sel(u: Array, v: Array) -> Array:
        cc = jnp.reshape(c, jnp.shape(c) + (1,) * (u.ndim - jnp.ndim(c)))
        return jnp.where(cc, u, v)

    return jax.tree.map(sel, a, b)


def _check_shapes(new: PyTree, example: PyTree, name: str, what: str) -> None:
    """Raise unless ``new`` has the structure and leaf shapes of ``example`` (``what``)."""
    if jax.tree.structure(new) != jax.tree.structure(example):
        raise TypeError(f"FixedLagSmoother.update({name}): expected the structure of the {what}")
    for a, b in zip(jax.tree.leaves(new), jax.tree.leaves(example), strict=True):
        if jnp.shape(a) != jnp.shape(b):
            raise ValueError(
                f"FixedLagSmoother.update({name}): leaf of shape "
                f"{jnp.shape(a)}, expected {jnp.shape(b)}"
            )


def _finite(x: PyTree, batch: int = 0) -> Array:
    """Whether every leaf of ``x`` is finite, per index of its ``batch`` leading axes."""

    def leaf(a: Array) -> Array:
        a = jnp.asarray(a)
        return jnp.all(jnp.isfinite(a).reshape(*a.shape[:batch], -1), axis=-1)

    leaves = jax.tree.leaves(x)
    return jnp.all(jnp.stack([leaf(a) for a in leaves]), axis=0) if leaves else jnp.asarray(True)


class FixedLagSmoother(eqx.Module):
    """Fixed-lag smoother over the last ``window`` states (module docstring).

    Build it with an example state and example step data (they fix shapes and dtypes;
    the window starts empty), then feed one state per step with :meth:`update`::

        sm = FixedLagSmoother(x_example, data_example, window=10, motion=f, unary=u)
        step = jax.jit(FixedLagSmoother.update)
        for guess, data in stream:
            sm = step(sm, guess, data)
        sm.latest(), sm.marginal_covariances()

    Residual functions return *whitened* residuals (multiply by the square-root
    information yourself); the cost is ``½‖r‖²`` summed over factors:

    * ``motion(x_prev, x, data) -> (r_m,)``: factors between consecutive states (e.g. a
      between / preintegrated IMU factor); not used for the very first state.
    * ``unary(x, data) -> (r_u,)``: factors on the new state alone (GPS, priors: put the
      prior on the first state here, e.g. weighted by a flag in ``data``).
    * ``loop(x_old, x, loop_data) -> (r_l,)``: up to ``max_loops`` factors per step to
      the state ``lag`` steps older (``1 ≤ lag``); those to states outside the window are
      dropped.

    Fields (all arrays, batchable with ``jax.vmap`` / ``eqx.filter_vmap`` over streams):
    ``states`` (K, ...) stacked states, ``data`` (K, ...) their step data, ``loop_lag``
    (K, M) int, ``loop_valid`` (K, M) bool, ``loop_data`` (K, M, ...), ``prior_info``
    (n, n) and ``prior_grad`` (n,) (without loop factors, ``max_loops=0``: (d, d) and
    (d,) on the oldest slot, the only one a prior can reach in a chain, and the window
    is solved with block-tridiagonal Cholesky in O(K·d³)), ``prior_point`` (K, ...)
    stacked linearisation point, ``frozen`` (K,) states in the prior,
    ``count`` () number of filled slots (≤ K), ``iterations`` () Gauss–Newton iterations of
    the last update (incremental mode: 1 if it re-linearised, else 0), ``status`` () int32
    :class:`~jaxpose.results.Results` code of the last update (``status_name``): CONVERGED
    (the change fell below ``tol``; incremental mode: a finite step), MAX_STEPS
    (``max_iterations`` ran out first) or NON_FINITE (a step was not finite, e.g. a
    singular window system, a state no factor determines: the estimate is the last
    finite iterate, the guess if the first step failed), ``lin`` (K, ...)
    the linearisation point (:meth:`linearization_point`) of the kept linearisation:
    for chains (``max_loops=0``; else None) the oldest-first elimination of the window
    (module docstring), ``msg_info`` (K, d, d) and ``msg_grad`` (K, d) the message into
    each slot, ``back_a`` (K, d), ``back_m`` (K, d, d) and ``back_chol`` (K, d, d) the
    back-substitution ``Δ_s = a_s + M_s·Δ_{s+1}`` and the lower Cholesky factor of the
    information of ``Δ_s`` given ``Δ_{s+1}``; with loop factors (else None) the window
    systems, ``window_info`` (n, n) the Gauss–Newton information, ``first_info`` (n, n)
    and ``first_grad`` (n,) the part of the factors touching slot 0 and the prior (what
    the next marginalisation eliminates). Incremental mode only (else None): ``phase``
    () the number of updates modulo ``relinearize_skip`` (the threshold is checked when
    it returns to 0).
    """

    states: PyTree
    data: PyTree
    loop_lag: Array
    loop_valid: Array
    loop_data: PyTree
    prior_info: Array
    prior_grad: Array
    prior_point: PyTree
    frozen: Array
    count: Array
    iterations: Array
    status: Array
    lin: PyTree
    msg_info: Array | None
    msg_grad: Array | None
    back_a: Array | None
    back_m: Array | None
    back_chol: Array | None
    window_info: Array | None
    first_info: Array | None
    first_grad: Array | None
    phase: Array | None
    motion: Callable[..., Array] = eqx.field(static=True)
    unary: Callable[..., Array] | None = eqx.field(static=True)
    loop: Callable[..., Array] | None = eqx.field(static=True)
    window: int = eqx.field(static=True)
    max_iterations: int = eqx.field(static=True)
    tol: float = eqx.field(static=True)
    exact_prior_jacobian: bool = eqx.field(static=True)
    first_estimate: bool = eqx.field(static=True)
    relinearize_threshold: float | None = eqx.field(static=True)
    relinearize_skip: int = eqx.field(static=True)
    chain: bool = eqx.field(static=True)

    def __init__(
        self,
        state: PyTree,
        data: PyTree,
        *,
        window: int,
        motion: Callable[..., Array],
        unary: Callable[..., Array] | None = None,
        loop: Callable[..., Array] | None = None,
        loop_data: PyTree = None,
        max_loops: int = 0,
        max_iterations: int = 10,
        tol: float | None = None,
        exact_prior_jacobian: bool = True,
        first_estimate: bool = True,
        relinearize_threshold: float | None = None,
        relinearize_skip: int = 1,
    ):
        """Args:
        state: an example state (pytree of groups and arrays, no batch axis).
        data: example step data (pytree passed to ``motion`` and ``unary``).
        window: number of states K kept (≥ 2).
        motion, unary, loop: residual functions (class docstring).
        loop_data: example data of one loop factor (required when ``max_loops > 0``).
        max_loops: loop factors per step M.
        max_iterations: Gauss–Newton iterations per update (at most).
        tol: stop when every component of the change of the estimate is below it
            (default 1e-8 in float64, 1e-4 in float32; the window systems of IMU
            streams are ill-conditioned, ~1e11, so round-off keeps changes ~1e-10).
        exact_prior_jacobian: chart Jacobian ``Jr⁻¹`` in the prior (module docstring;
            only used with ``first_estimate=False``).
        first_estimate: first-estimate Jacobians: every factor is linearised at the
            prior's linearisation point for the states in the prior (module docstring).
        relinearize_threshold: None (default) for Gauss–Newton to convergence at every
            update; a float ≥ 0 for incremental updates (module docstring, *Incremental
            updates*): a state is re-linearised only when its step from its
            linearisation point exceeds it (largest tangent component, iSAM2's
            ``relinearizeThreshold``). Needs ``max_loops=0`` and ``first_estimate=True``.
        relinearize_skip: incremental mode: check the threshold at every n-th update
            only (iSAM2's ``relinearizeSkip``; default 1, every update); non-finite steps
            re-linearise at once.
        """
        if not callable(motion):
            raise TypeError("FixedLagSmoother(motion): expected a callable")
        for name, fn in (("unary", unary), ("loop", loop)):
            if fn is not None and not callable(fn):
                raise TypeError(f"FixedLagSmoother({name}): expected a callable or None")
        window = check_count(window, "FixedLagSmoother(window)", minimum=2)
        max_loops = check_count(max_loops, "FixedLagSmoother(max_loops)", minimum=0)
        if max_loops > 0 and (loop is None or loop_data is None):
            raise ValueError("FixedLagSmoother(max_loops > 0): needs loop and loop_data")
        if max_loops == 0 and (loop is not None or loop_data is not None):
            raise ValueError(
                "FixedLagSmoother(loop, loop_data): loop factors need slots: set max_loops "
                "(the most loop factors one update adds), else they would be ignored"
            )
        max_iterations = check_count(max_iterations, "FixedLagSmoother(max_iterations)")
        leaves = jax.tree.leaves(state)
        if not leaves or not all(
            jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) for a in leaves
        ):
            raise TypeError(
                "FixedLagSmoother(state): expected a pytree of float arrays and Lie groups"
            )
        dtype = jnp.result_type(*leaves)
        d = manifold.tangent_size(state)
        k, m = window, max_loops
        self.states = _stack(state, k)
        self.prior_point = _stack(state, k)
        self.data = _stack(data, k)
        self.loop_lag = jnp.ones((k, m), jnp.int32)
        self.loop_valid = jnp.zeros((k, m), bool)
        self.loop_data = _stack(_stack(loop_data, m), k) if m else None
        # without loop factors the window system is block tridiagonal and the prior
        # only ever lives on the oldest slot: (d, d) storage, block-tridiagonal solves
        self.chain = m == 0
        p = d if self.chain else k * d
        self.prior_info = jnp.zeros((p, p), dtype)
        self.prior_grad = jnp.zeros((p,), dtype)
        self.frozen = jnp.zeros((k,), bool)
        self.count = jnp.zeros((), jnp.int32)
        self.iterations = jnp.zeros((), jnp.int32)
        self.status = jnp.asarray(Results.CONVERGED, jnp.int32)
        self.motion, self.unary, self.loop = motion, unary, loop
        self.window, self.max_iterations = window, max_iterations
        eps = jnp.finfo(dtype).eps
        if tol is not None and (isinstance(tol, bool) or not isinstance(tol, numbers.Real)
                                or not 0 < tol < math.inf):
            raise ValueError(f"FixedLagSmoother(tol): expected a finite float > 0 or None, "
                             f"got {tol!r}")
        self.tol = float(tol) if tol is not None else (1e-8 if eps < 1e-10 else 1e-4)
        self.exact_prior_jacobian = bool(exact_prior_jacobian)
        self.first_estimate = bool(first_estimate)
        relinearize_skip = check_count(relinearize_skip, "FixedLagSmoother(relinearize_skip)")
        if relinearize_skip != 1 and relinearize_threshold is None:
            raise ValueError(
                "FixedLagSmoother(relinearize_skip): only used by incremental updates; set "
                "relinearize_threshold too"
            )
        if relinearize_threshold is not None:
            if not self.chain or not self.first_estimate:
                raise ValueError(
                    "FixedLagSmoother(relinearize_threshold): incremental updates need "
                    "max_loops=0 and first_estimate=True"
                )
            if not relinearize_threshold >= 0:
                raise ValueError(
                    "FixedLagSmoother(relinearize_threshold): expected a float >= 0 or None, "
                    f"got {relinearize_threshold!r}"
                )
            relinearize_threshold = float(relinearize_threshold)
            self.phase = jnp.zeros((), jnp.int32)
        else:
            self.phase = None
        self.lin = _stack(state, k)
        if self.chain:
            self.msg_info = jnp.zeros((k, d, d), dtype)
            self.msg_grad = jnp.zeros((k, d), dtype)
            self.back_a = jnp.zeros((k, d), dtype)
            self.back_m = jnp.zeros((k, d, d), dtype)
            self.back_chol = jnp.zeros((k, d, d), dtype)
            self.window_info = self.first_info = self.first_grad = None
        else:
            self.msg_info = self.msg_grad = self.back_a = self.back_m = self.back_chol = None
            self.window_info = jnp.zeros((p, p), dtype)
            self.first_info = jnp.zeros((p, p), dtype)
            self.first_grad = jnp.zeros((p,), dtype)
        self.relinearize_threshold = relinearize_threshold
        self.relinearize_skip = relinearize_skip

    # ------------------------------------------------------------------ helpers
    @property
    def tangent_dim(self) -> int:
        """Tangent size d of one state."""
        return manifold.tangent_size(_take(self.states, 0))

    @property
    def status_name(self) -> str | Any:
        """``status`` as text (``"converged"``, ``"max_steps"``, ``"non_finite"``)."""
        return Results.name_of(self.status)

    @property
    def valid(self) -> Array:
        """(K,) bool: slots holding a state (the last ``min(count, K)``)."""
        return jnp.arange(self.window) >= self.window - self.count

    def latest(self) -> PyTree:
        """The newest state estimate."""
        return _take(self.states, self.window - 1)

    def linearization_point(self) -> PyTree:
        """(K, ...) where the kept linearisation was computed (``lin``): the prior's
        point for the states in the prior (with first-estimate Jacobians); elsewhere the
        Gauss–Newton iterate of the last step (the estimate is that point ⊕ the last
        step, below ``tol`` at convergence), or in incremental mode the point of the
        last re-linearisation."""
        return self.lin

    def _unravel(self) -> Callable[[Array], PyTree]:
        return manifold.flat_tangent(_take(self.states, 0))[1]

    def _plus(self, x: PyTree, e: Array, method: str = "retract") -> PyTree:
        """``x ⊕ e`` by :mod:`jaxpose.lie.manifold`'s ``method`` (``retract_linear`` for
        Jacobians at e = 0)."""
        return getattr(manifold, method)(x, self._unravel()(e))

    def _minus(self, x: PyTree, y: PyTree) -> Array:
        return ravel_pytree(manifold.rminus(x, y))[0]

    def _pair_terms(self, fn, xa, xb, data, d):
        """Residuals (m, r) and Jacobians (m, r, d) w.r.t. both ends of vmapped pairs."""

        def one(a, b, dat):
            def f(e):
                lin = "retract_linear"
                r = fn(self._plus(a, e[:d], lin), self._plus(b, e[d:], lin), dat)
                return r.astype(self.prior_grad.dtype)  # see _unary_terms

            z = jnp.zeros(2 * d, self.prior_grad.dtype)
            r = f(z)
            j = jax.jacfwd(f)(z)
            return r, j[:, :d], j[:, d:]

        return jax.vmap(one)(xa, xb, data)

    def _prior_dense(self) -> tuple[Array, Array]:
        """The prior as (n, n) information and (n,) gradient."""
        if not self.chain:
            return self.prior_info, self.prior_grad
        n, d = self.window * self.tangent_dim, self.tangent_dim
        info = jnp.zeros((n, n), self.prior_info.dtype).at[:d, :d].set(self.prior_info)
        return info, jnp.zeros((n,), self.prior_grad.dtype).at[:d].set(self.prior_grad)

    def _unary_terms(self, x: PyTree, slots: Array) -> tuple[Array, Array]:
        """Residuals (m, r) and Jacobians (m, r, d) of the unary factors of stacked x, the
        states of ``slots`` (m,)."""
        unary, d = self.unary, self.tangent_dim

        def one(xs, dat):
            def f(e):
                # float64 data keep their precision in the residual (ECEF coordinates,
                # epoch times); the residual is rounded to the state's dtype
                r = unary(self._plus(xs, e, "retract_linear"), dat)
                return r.astype(self.prior_grad.dtype)

            z = jnp.zeros(d, self.prior_grad.dtype)
            return f(z), jax.jacfwd(f)(z)

        return jax.vmap(one)(x, _take(self.data, slots))

    def _prior_terms(self, y0: PyTree, xb0: PyTree) -> tuple[Array, Array, Array]:
        """Chain prior at slot 0: (d, d) information, (d,) gradient and cost at y0."""
        d = self.tangent_dim
        delta = self._minus(y0, xb0)
        if self.exact_prior_jacobian:
            jac = jax.jacfwd(lambda e: self._minus(self._plus(y0, e, "retract_linear"), xb0))(
                jnp.zeros(d, delta.dtype)
            )
        else:
            jac = jnp.eye(d, dtype=delta.dtype)
        p, gp = self.prior_info, self.prior_grad
        cost = gp @ delta + 0.5 * delta @ (p @ delta)
        return jac.T @ p @ jac, jac.T @ (p @ delta + gp), cost

    def _chain_terms(
        self, y: PyTree, slots: Array, pairs: bool = True
    ) -> tuple[Array, Array, tuple[Array, ...] | None]:
        """Gauss–Newton blocks of the window ``y`` at ``slots`` (n,) (chain case, masked
        by :attr:`valid`): the unary information (n, d, d) and gradient (n, d) of each
        slot and, with ``pairs``, the blocks ``(AᵀA, AᵀB, BᵀB, Aᵀr, Bᵀr)`` (n, ...) of the
        motion factor from each slot to the next (zero for the newest slot)."""
        k, d = self.window, self.tangent_dim
        valid = self.valid
        dtype = self.prior_grad.dtype
        info = jnp.zeros((slots.shape[0], d, d), dtype)
        grad = jnp.zeros((slots.shape[0], d), dtype)
        if self.unary is not None:
            ru, ju = self._unary_terms(_take(y, slots), slots)
            ok = valid[slots]
            ju = jnp.where(ok[:, None, None], ju, 0.0)
            ru = jnp.where(ok[:, None], ru, 0.0)
            info, grad = small_matmul(ju.mT, ju), jnp.einsum("mra,mr->ma", ju, ru)
        if not pairs:
            return info, grad, None
        nxt = jnp.minimum(slots + 1, k - 1)
        r, ja, jb = self._pair_terms(
            self.motion, _take(y, slots), _take(y, nxt), _take(self.data, nxt), d
        )
        mask = (valid[slots] & valid[nxt] & (slots < k - 1))[:, None, None]
        ja, jb = jnp.where(mask, ja, 0.0), jnp.where(mask, jb, 0.0)
        r = jnp.where(mask[:, :, 0], r, 0.0)
        blocks = (
            small_matmul(ja.mT, ja),
            small_matmul(ja.mT, jb),
            small_matmul(jb.mT, jb),
            jnp.einsum("mra,mr->ma", ja, r),
            jnp.einsum("mra,mr->ma", jb, r),
        )
        return info, grad, blocks

    def _elimination_step(self, msg, unary, empty, pair):
        """Eliminate one slot (see :meth:`_eliminate`): ``msg`` (info, grad) into it,
        its ``unary`` (info, grad), ``empty`` (d, d) identity if the slot is empty, the
        ``pair`` blocks of its motion factor to the next slot. Returns the message into
        the next slot, ``a_s``, ``M_s`` and the lower Cholesky factor ``L_s`` of
        ``Λ_s + AᵀA`` (``C_s = L_s⁻ᵀL_s⁻¹``)."""
        d = self.tangent_dim
        aa, ab, bb, ar, br = pair
        cf = jsl.cho_factor(msg[0] + unary[0] + aa + empty, lower=True)
        rhs = jnp.concatenate([ab, (msg[1] + unary[1] + ar)[:, None]], axis=1)
        sol = -jsl.cho_solve(cf, rhs)
        m_s, a_s = sol[:, :d], sol[:, d]
        return (bb + ab.T @ m_s, br + ab.T @ a_s), a_s, m_s, cf[0]

    @staticmethod
    def _newest_step(msg, unary, empty) -> tuple[Array, Array]:
        """``a`` and ``L`` of the newest slot of an elimination (no factor to a next
        slot): its step and the lower Cholesky factor of its information ``Λ``."""
        cf = jsl.cho_factor(msg[0] + unary[0] + empty, lower=True)
        return -jsl.cho_solve(cf, msg[1] + unary[1]), cf[0]

    def _empty_blocks(self, slots: Array) -> Array:
        """(n, d, d) identity for the empty slots among ``slots``, zero elsewhere."""
        eye = jnp.eye(self.tangent_dim, dtype=self.prior_grad.dtype)
        return (~self.valid[slots]).astype(eye.dtype)[:, None, None] * eye

    def _eliminate(
        self, y: PyTree, lo: int, hi: int, msg_info: Array, msg_grad: Array
    ) -> tuple[Array, Array, Array, Array]:
        """Eliminate slots ``lo..hi−1`` of the chain window ``y``, oldest first, given the
        message ``(msg_info (d, d), msg_grad (d,))`` into slot ``lo`` (the prior when
        ``lo = 0``), ignoring the factors beyond ``hi``.

        Slot s holds ``Λ_s = msg_s + unary_s`` and the motion factor (s, s+1) with blocks
        A, B and residual r. Eliminating s leaves the message into s+1,
        ``msg_{s+1} = (BᵀB + BᵀA·M_s, Bᵀr + BᵀA·a_s)``, and the back-substitution
        ``Δ_s = a_s + M_s·Δ_{s+1}`` with ``[M_s, a_s] = −(Λ_s + AᵀA)⁻¹[AᵀB, η_s + Aᵀr]``
        (``M_{hi−1} = 0``). Empty slots get an identity block (their Δ is 0).

        The conditional covariance of ``Δ_s`` given ``Δ_{s+1}`` is ``C_s = (Λ_s +
        AᵀA)⁻¹`` (``Λ⁻¹`` for the newest slot), so the marginal covariances follow from
        ``Σ_s = C_s + M_s·Σ_{s+1}·M_sᵀ`` (:meth:`marginal_covariances`).

        Returns the messages (n, d, d), (n, d) into slots ``lo..hi−1`` (the first is the
        input), ``a`` (n, d), ``M`` (n, d, d) and ``L`` (n, d, d) the lower Cholesky
        factors of ``C⁻¹``, ``n = hi − lo``.
        """
        slots = jnp.arange(lo, hi)
        info, grad, pairs = self._chain_terms(y, slots)
        empty = self._empty_blocks(slots)

        def step(msg, inp):
            u_info, u_grad, empty_s, pair = inp
            nxt, a_s, m_s, l_s = self._elimination_step(msg, (u_info, u_grad), empty_s, pair)
            return nxt, (nxt, a_s, m_s, l_s)

        head = jax.tree.map(lambda v: v[:-1], (info, grad, empty, pairs))
        last, ((infos, grads), a, m, chol) = jax.lax.scan(step, (msg_info, msg_grad), head)
        a_last, l_last = self._newest_step(last, (info[-1], grad[-1]), empty[-1])
        return (
            jnp.concatenate([msg_info[None], infos]),
            jnp.concatenate([msg_grad[None], grads]),
            jnp.concatenate([a, a_last[None]]),
            jnp.concatenate([m, jnp.zeros_like(empty[:1])]),
            jnp.concatenate([chol, l_last[None]]),
        )

    def _reeliminate(self, lo: Array) -> FixedLagSmoother:
        """Incremental mode: eliminate slots ``lo..K−1`` (``lo`` traced) at ``lin`` again,
        from the cached message into ``lo``, and update the cache; the slots before
        ``lo`` keep theirs. Costs ``O((K − lo)·d³)``."""
        k = self.window

        def cond(c):
            return c[0] < k - 1

        def body(c):
            s, info, grad, a, m, chol = c
            u_info, u_grad, pair = self._chain_terms(self.lin, s[None])
            (ni, ng), a_s, m_s, l_s = self._elimination_step(
                (info[s], grad[s]),
                (u_info[0], u_grad[0]),
                self._empty_blocks(s[None])[0],
                jax.tree.map(lambda v: v[0], pair),
            )
            info, grad = info.at[s + 1].set(ni), grad.at[s + 1].set(ng)
            return s + 1, info, grad, a.at[s].set(a_s), m.at[s].set(m_s), chol.at[s].set(l_s)

        _, info, grad, a, m, chol = jax.lax.while_loop(
            cond, body, (jnp.asarray(lo), *self._linearization()))
        newest = jnp.arange(k - 1, k)
        u_info, u_grad, _ = self._chain_terms(self.lin, newest, pairs=False)
        a_last, l_last = self._newest_step(
            (info[-1], grad[-1]), (u_info[0], u_grad[0]), self._empty_blocks(newest)[0]
        )
        return self._with_linearization(
            (info, grad, a.at[-1].set(a_last), m.at[-1].set(0.0), chol.at[-1].set(l_last)))

    def _linearization(self) -> tuple[Array, ...]:
        """The kept linearisation at the linearisation point: the elimination ``(msg_info,
        msg_grad, back_a, back_m, back_chol)`` of a chain, else ``(window_info,
        first_info, first_grad)``."""
        if self.chain:
            return self.msg_info, self.msg_grad, self.back_a, self.back_m, self.back_chol
        return self.window_info, self.first_info, self.first_grad

    def _with_linearization(self, cache: tuple[Array, ...]) -> FixedLagSmoother:
        """This smoother keeping ``cache`` (as :meth:`_linearization` returns it)."""
        if self.chain:
            return eqx.tree_at(
                lambda s: (s.msg_info, s.msg_grad, s.back_a, s.back_m, s.back_chol), self, cache)
        return eqx.tree_at(lambda s: (s.window_info, s.first_info, s.first_grad), self, cache)

    @staticmethod
    def _back_substitute(a: Array, m: Array) -> Array:
        """``Δ_s = a_s + M_s·Δ_{s+1}`` from the newest slot back, (K, d)."""

        def step(nxt, inp):
            a_s, m_s = inp
            x = a_s + m_s @ nxt
            return x, x

        _, xs = jax.lax.scan(step, jnp.zeros_like(a[0]), (a, m), reverse=True)
        return xs

    def _system(self, x: PyTree) -> tuple[tuple[Array, Array, Array], tuple[Array, Array]]:
        """Gauss–Newton systems at ``x`` from one linearisation: ``(H (n, n), g (n,),
        cost)`` of every factor and the prior, and ``(H, g)`` of the factors touching
        slot 0 and the prior (what marginalisation eliminates)."""
        k, d = self.window, self.tangent_dim
        dtype = self.prior_grad.dtype
        valid = self.valid
        zero = (jnp.zeros((k, d, k, d), dtype), jnp.zeros((k, d), dtype))
        acc = (*zero, jnp.zeros((), dtype)), zero

        def add(acc, a, b, r, ja, jb, mask):
            mask = mask.astype(bool)
            r = jnp.where(mask[:, None], r, 0.0)
            ja = jnp.where(mask[:, None, None], ja, 0.0)
            jb = jnp.where(mask[:, None, None], jb, 0.0)
            blocks = ((a, a, small_matmul(ja.mT, ja)), (a, b, small_matmul(ja.mT, jb)),
                      (b, a, small_matmul(jb.mT, ja)), (b, b, small_matmul(jb.mT, jb)))
            grads = ((a, jnp.einsum("mra,mr->ma", ja, r)), (b, jnp.einsum("mra,mr->ma", jb, r)))
            first = (a == 0) | (b == 0)  # the factors touching slot 0
            out = []
            for (h, g), w in ((acc[0][:2], jnp.ones_like(first)), (acc[1], first)):
                for i, j, blk in blocks:
                    h = h.at[i, :, j, :].add(jnp.where(w[:, None, None], blk, 0.0))
                for i, gr in grads:
                    g = g.at[i].add(jnp.where(w[:, None], gr, 0.0))
                out.append((h, g))
            return (*out[0], acc[0][2] + 0.5 * jnp.sum(r * r)), out[1]

        slots = jnp.arange(k)
        # motion factors (s-1, s), s = 1..K-1
        a, b = slots[:-1], slots[1:]
        r, ja, jb = self._pair_terms(self.motion, _take(x, a), _take(x, b), _take(self.data, b), d)
        acc = add(acc, a, b, r, ja, jb, valid[a] & valid[b])
        # unary factors
        if self.unary is not None:
            r, ju = self._unary_terms(x, slots)
            acc = add(acc, slots, slots, r, ju, jnp.zeros_like(ju), valid)
        # loop factors (s - lag, s)
        m = self.loop_lag.shape[1]
        if self.loop is not None and m > 0:
            b = jnp.repeat(slots, m)
            lag = self.loop_lag.reshape(-1)
            a = b - lag
            ok = (a >= 0) & (lag >= 1) & self.loop_valid.reshape(-1)
            a = jnp.clip(a, 0, k - 1)
            ok = ok & valid[a] & valid[b]
            ld = jax.tree.map(lambda v: v.reshape(k * m, *v.shape[2:]), self.loop_data)
            r, ja, jb = self._pair_terms(self.loop, _take(x, a), _take(x, b), ld, d)
            acc = add(acc, a, b, r, ja, jb, ok)
        # prior: g_pᵀδ + ½δᵀH_pδ, δ = x ⊖ x̄ per slot
        pinfo, pgrad = self._prior_dense()
        delta = jax.vmap(self._minus)(x, self.prior_point)  # (K, d)
        if self.exact_prior_jacobian:

            def chart(xs, xb):
                return jax.jacfwd(lambda e: self._minus(self._plus(xs, e, "retract_linear"), xb))(
                    jnp.zeros(d, dtype))

            jac = jax.vmap(chart)(x, self.prior_point)  # (K, d, d)
        else:
            jac = jnp.broadcast_to(jnp.eye(d, dtype=dtype), (k, d, d))
        dv = delta.reshape(-1)
        hp = jnp.einsum("iab,iajc,jcd->ibjd", jac, pinfo.reshape(k, d, k, d), jac)
        gp = jnp.einsum("iab,ia->ib", jac, (pinfo @ dv + pgrad).reshape(k, d))
        (h, g, cost), (h1, g1) = acc
        n = k * d
        full = ((h + hp).reshape(n, n), (g + gp).reshape(n),
                cost + pgrad @ dv + 0.5 * dv @ (pinfo @ dv))
        return full, ((h1 + hp).reshape(n, n), (g1 + gp).reshape(n))

    def _regularised(self, h: Array) -> Array:
        """Identity on the diagonal blocks of empty slots (their step is then zero)."""
        d = self.tangent_dim
        empty = jnp.repeat(~self.valid, d).astype(h.dtype)
        return h + jnp.diag(empty)

    def _optimize(self) -> FixedLagSmoother:
        """Gauss–Newton on the window until the largest change of the estimate is below
        ``tol`` (at most ``max_iterations`` steps). The smoother keeps the linearisation
        the last step was computed from and its point ``lin`` (the chain's elimination or
        the dense window systems): the next marginalisation and
        :meth:`marginal_covariances` read it instead of linearising the factors again, so
        an update's program traces them once and computes them once per iteration."""
        k, d = self.window, self.tangent_dim

        def body(c):
            x, it, _, lin_prev, cache_prev = c
            y = _where(self.frozen, self.prior_point, x)
            if self.chain:
                hp, gp, _ = self._prior_terms(_take(y, 0), _take(self.prior_point, 0))
                cache = self._eliminate(y, 0, k, hp, gp)
                step = self._back_substitute(cache[2], cache[3])
            else:
                (h, g, _), (h1, g1) = self._system(y)
                cache = (h, h1, g1)
                step = -jsl.cho_solve(jsl.cho_factor(self._regularised(h)), g)
            ok = jnp.all(jnp.isfinite(step))
            step = jnp.where(ok, step, 0.0).reshape(k, d)
            # a step that is not finite (the factors are not finite at y: a previous step
            # left their domain) goes back to the last point of this update whose
            # linearisation was finite, and keeps that linearisation: a non-finite one
            # would become the next prior at marginalisation, for every later update
            back = ~ok & (it > 0)
            x_new = _where(ok, jax.vmap(self._plus)(y, step), _where(back, lin_prev, x))
            y = _where(back, lin_prev, y)
            cache = _where(back, cache_prev, cache)
            change = jax.vmap(self._minus)(x_new, x)
            small = jnp.max(jnp.abs(change)) < self.tol
            status = jnp.where(~ok, Results.NON_FINITE, jnp.where(
                small, Results.CONVERGED, jnp.where(
                    it + 1 >= self.max_iterations, Results.MAX_STEPS, Results.RUNNING)))
            return x_new, it + 1, status.astype(jnp.int32), y, cache

        start = (self.states, jnp.zeros((), jnp.int32), jnp.asarray(Results.RUNNING, jnp.int32),
                 self.lin, self._linearization())
        x, it, status, lin, cache = jax.lax.while_loop(lambda c: c[2] < 0, body, start)
        return eqx.tree_at(lambda s: (s.states, s.iterations, s.status, s.lin),
                           self._with_linearization(cache), (x, it, status, lin))

    def _marginalize_first(self) -> tuple[Array, Array, Array]:
        """Prior on slots 1..K-1 (shifted to 0..K-2, last slot empty) after eliminating
        slot 0 at the linearisation point, and the (K,) slots it couples (shifted)."""
        k, d = self.window, self.tangent_dim
        if self.chain:
            return self._marginalize_chain()
        h, g = self.first_info, self.first_grad
        coupled = jnp.any(h[:d].reshape(d, k, d) != 0, axis=(0, 2)) | self.frozen
        coupled = jnp.concatenate([coupled[1:], jnp.zeros((1,), bool)])
        h00, h0r, hrr = h[:d, :d], h[:d, d:], h[d:, d:]
        g0, gr = g[:d], g[d:]
        cf = jsl.cho_factor(h00)
        hn = hrr - h0r.T @ jsl.cho_solve(cf, h0r)
        gn = gr - h0r.T @ jsl.cho_solve(cf, g0)
        hn = 0.5 * (hn + hn.T)
        info = jnp.zeros_like(self.prior_info).at[: (k - 1) * d, : (k - 1) * d].set(hn)
        grad = jnp.zeros_like(self.prior_grad).at[: (k - 1) * d].set(gn)
        return info, grad, coupled

    def _marginalize_chain(self) -> tuple[Array, Array, Array]:
        """Chain case of :meth:`_marginalize_first`: the new prior lives on slot 1, the
        message out of slot 0 of the cached elimination at the linearisation point."""
        info, grad = self.msg_info[1], self.msg_grad[1]
        coupled = jnp.zeros((self.window,), bool).at[0].set(True)
        return 0.5 * (info + info.T), grad, coupled

    def _step_from_cache(self, relinearized: int) -> tuple[FixedLagSmoother, Array]:
        """Incremental mode: back-substitute the cached elimination and move to
        ``lin ⊕ Δ``; also return Δ (K, d), +inf where the step is not finite (then the
        estimate stays at ``lin``)."""
        delta = self._back_substitute(self.back_a, self.back_m)
        ok = jnp.all(jnp.isfinite(delta))
        states = jax.vmap(self._plus)(self.lin, jnp.where(ok, delta, 0.0))
        new = eqx.tree_at(
            lambda s: (s.states, s.iterations), self, (states, jnp.asarray(relinearized, jnp.int32))
        )
        return new, jnp.where(ok, delta, jnp.inf)

    def _incremental(self) -> FixedLagSmoother:
        """Incremental solve after the shift (module docstring): eliminate the last two
        slots (the new motion and unary factors) from the cached message, back-substitute;
        then re-linearise the non-frozen states whose step exceeds the threshold (checked
        when ``phase`` is 0; a step that is not finite, at once) at their estimate and
        eliminate again from the oldest of them. Both passes are one loop body, so the
        factors' linearisation is traced once."""
        k = self.window
        moving = self.valid & ~self.frozen

        def body(c):
            s_in, lo, passes, _, lin_in = c
            s, delta = s_in._reeliminate(lo)._step_from_cache(passes)
            largest = jnp.max(jnp.abs(delta), axis=1)  # +inf where the step is not finite
            check = (self.phase == 0) | ~jnp.isfinite(largest)
            finite = jnp.all(jnp.isfinite(largest))
            # a relinearisation that is not finite (the previous step left the factors'
            # domain) goes back to the previous pass: its linearisation (finite) and its
            # point lin_in, so no non-finite linearisation becomes the next prior
            back = ~finite & (passes > 0)
            exceed = (moving & check & ~(largest <= self.relinearize_threshold)
                      & (passes == 0) & ~back)
            status = jnp.where(finite, Results.CONVERGED, Results.NON_FINITE).astype(jnp.int32)
            lin_used = s.lin  # the point this pass's linearisation is from
            s = eqx.tree_at(lambda t: (t.lin, t.status), s,
                            (_where(exceed, s.states, s.lin), status))
            reverted = eqx.tree_at(lambda t: (t.lin, t.states, t.status), s_in,
                                   (lin_in, lin_in, status))
            s = _where(back, reverted, s)
            return (s, jnp.maximum(jnp.argmax(exceed) - 1, 0), passes + 1, jnp.any(exceed),
                    lin_used)

        # a cached elimination that is not finite (left by a non_finite update) would
        # pass NaN messages on for good: eliminate the whole window again from the prior
        start = (self, jnp.where(_finite(self._linearization()), k - 2, 0),
                 jnp.zeros((), jnp.int32), jnp.zeros((), bool), self.lin)
        return jax.lax.while_loop(lambda c: (c[2] == 0) | c[3], body, start)[0]

    # ------------------------------------------------------------------ public
    @full_precision
    def update(
        self,
        guess: PyTree,
        data: PyTree,
        loop_lag: Any = None,
        loop_valid: Any = None,
        loop_data: PyTree = None,
    ) -> FixedLagSmoother:
        """Add one state (initial value ``guess``) and the factors of its step, solve the
        window and return the new smoother (marginalising the oldest state first when
        the window is full).

        Args:
            guess: initial value of the new state (same structure as the example state).
            data: the step's data (same structure as the example data).
            loop_lag: (M,) ints ≥ 1, loop factor m links the state ``loop_lag[m]`` steps
                older to the new one; loop_valid (M,) bool; loop_data (M, ...).
        """
        k, d = self.window, self.tangent_dim
        _check_shapes(guess, _take(self.states, 0), "guess", "example state")
        _check_shapes(data, _take(self.data, 0), "data", "example data")
        m = self.loop_lag.shape[1]
        if not m and not (loop_lag is None and loop_valid is None and loop_data is None):
            raise ValueError(
                "FixedLagSmoother.update: loop_lag, loop_valid or loop_data given to a smoother "
                "without loop factors (max_loops=0): they would be ignored; build it with "
                "loop=, loop_data= and max_loops > 0"
            )
        if m:
            if loop_lag is None or loop_valid is None or loop_data is None:
                raise ValueError(
                    "FixedLagSmoother.update: this smoother has max_loops > 0; "
                    "pass loop_lag, loop_valid and loop_data"
                )
            lag = jnp.asarray(loop_lag)
            if not jnp.issubdtype(lag.dtype, jnp.integer):
                raise TypeError(
                    f"FixedLagSmoother.update(loop_lag): expected integers, got {lag.dtype}"
                )
            lag = lag.astype(jnp.int32)
            lv = jnp.asarray(loop_valid, bool)
            if lag.shape != (m,) or lv.shape != (m,):
                raise ValueError(
                    f"FixedLagSmoother.update(loop_lag, loop_valid): expected "
                    f"shape ({m},), got {lag.shape} and {lv.shape}"
                )
            _check_shapes(loop_data, _take(self.loop_data, 0), "loop_data",
                          "example loop data (M, ...)")
            lag = runtime_check(
                lag, jnp.any(lv & (lag < 1)),
                "FixedLagSmoother.update(loop_lag): a valid loop factor needs lag >= 1",
            )
            loop_data = runtime_check(
                loop_data, jnp.any(lv & ~_finite(loop_data, 1)),
                "FixedLagSmoother.update(loop_data): non-finite values in a valid loop factor",
            )
        guess = keep_dtypes(guess, _take(self.states, 0))  # the states' dtypes
        guess = eqx.error_if(
            guess, ~jnp.all(_finite(guess)), "FixedLagSmoother.update(guess): non-finite values"
        )
        data = runtime_check(
            data, ~jnp.all(_finite(data)), "FixedLagSmoother.update(data): non-finite values"
        )
        full = self.valid[0]
        info_m, grad_m, coupled = self._marginalize_first()
        # the oldest state's information enters the prior only from a finite
        # linearisation: one that is not (the update that made it was non_finite, e.g. a
        # guess outside a factor's domain) is dropped with the state, else the prior
        # would be NaN for every later update
        marginalize = full & _finite((info_m, grad_m))
        if self.chain:  # before the first marginalisation the prior is empty
            info_s = jnp.where(full, 0.0, self.prior_info)
            grad_s = jnp.where(full, 0.0, self.prior_grad)
        else:
            dd = (k - 1) * d
            info_s = jnp.zeros_like(self.prior_info).at[:dd, :dd].set(self.prior_info[d:, d:])
            grad_s = jnp.zeros_like(self.prior_grad).at[:dd].set(self.prior_grad[d:])
        info = jnp.where(marginalize, info_m, info_s)
        grad = jnp.where(marginalize, grad_m, grad_s)
        # a new prior is anchored at the linearisation point; else unchanged
        point = _shift_in(_where(marginalize, self.linearization_point(), self.prior_point),
                          guess)
        frozen = _shift_in(self.frozen, jnp.zeros((), bool))
        if self.first_estimate:
            frozen = jnp.where(marginalize, coupled, frozen)
        new = eqx.tree_at(
            lambda s: (
                s.states,
                s.data,
                s.prior_info,
                s.prior_grad,
                s.prior_point,
                s.frozen,
                s.count,
            ),
            self,
            (
                _shift_in(self.states, guess),
                _shift_in(self.data, data),
                info,
                grad,
                point,
                frozen,
                jnp.minimum(self.count + 1, k),
            ),
        )
        if m:
            new = eqx.tree_at(
                lambda s: (s.loop_lag, s.loop_valid, s.loop_data),
                new,
                (
                    _shift_in(self.loop_lag, lag),
                    _shift_in(self.loop_valid, lv),
                    _shift_in(self.loop_data, loop_data),
                ),
            )
        if self.relinearize_threshold is not None:
            cache = tuple(_shift_in(v, jnp.zeros_like(v[0])) for v in self._linearization())
            # the message into the new oldest slot is the new prior: the marginalised one,
            # or (a state dropped without its information, above) the shifted prior
            cache = (cache[0].at[0].set(jnp.where(marginalize, cache[0][0], info)),
                     cache[1].at[0].set(jnp.where(marginalize, cache[1][0], grad)), *cache[2:])
            new = eqx.tree_at(
                lambda s: (s.lin, s.phase),
                new._with_linearization(cache),
                (_shift_in(self.lin, guess), (self.phase + 1) % self.relinearize_skip),
            )
            return forward_mode_only(new._incremental(), _REVERSE_MODE)
        return forward_mode_only(new._optimize(), _REVERSE_MODE)

    def information(self) -> Array:
        """(n, n) Gauss–Newton information of the window at the linearisation point
        (empty slots: identity blocks), tangent layout slot-major."""
        if self.chain:
            return self._regularised(self._system(self.linearization_point())[0][0])
        return self._regularised(self.window_info)

    def cost(self) -> Array:
        """Window cost ``½Σ‖r‖² + prior`` at the current estimate."""
        return self._system(self.states)[0][2]

    @full_precision
    def marginal_covariances(self) -> Array:
        """(K, d, d) marginal covariances of the window states (blocks of the inverse
        window information at the linearisation point, in each state's right tangent
        chart; NaN for empty slots). Chains read them off the cached elimination,
        newest first: ``Σ_s = C_s + M_s·Σ_{s+1}·M_sᵀ`` (:meth:`_eliminate`)."""
        k, d = self.window, self.tangent_dim
        if self.chain:
            eye = jnp.eye(d, dtype=self.back_chol.dtype)
            cond = jax.vmap(lambda low: jsl.cho_solve((low, True), eye))(self.back_chol)

            def step(nxt, inp):
                m_s, c_s = inp
                cov = c_s + m_s @ nxt @ m_s.T
                return cov, cov

            _, older = jax.lax.scan(step, cond[-1], (self.back_m[:-1], cond[:-1]),
                                    reverse=True)
            blocks = jnp.concatenate([older, cond[-1:]])
            blocks = 0.5 * (blocks + blocks.mT)
        else:
            h = self.information()
            cov = jsl.cho_solve(jsl.cho_factor(h), jnp.eye(k * d, dtype=h.dtype))
            blocks = cov.reshape(k, d, k, d)[jnp.arange(k), :, jnp.arange(k), :]
        return jnp.where(self.valid[:, None, None], blocks, jnp.nan)
