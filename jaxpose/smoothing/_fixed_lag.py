"""Fixed-lag smoothing over a window of the last ``K`` states.

The smoother holds the last ``K`` states of a stream in fixed-shape arrays (a shift
register: slot 0 is the oldest, slot ``K − 1`` the newest) together with the data of the
factors attached to them and a Gaussian prior on the window (the marginalised past).
Each :meth:`FixedLagSmoother.update`:

1. marginalises the oldest state, if the window is full: the factors touching slot 0
   (its unary factors, the motion factor to slot 1, loop factors ending in slot 0) and
   the current prior are linearised at the linearisation point (below) and slot 0 is
   eliminated (Schur complement). The result is the new prior, stored as information
   ``H_p`` (n, n) and gradient ``g_p`` (n,) in the tangent chart at a linearisation point
   ``x̄`` (the linearisation point at marginalisation time): ``cost_p(x) = g_pᵀδ +
   ½δᵀH_pδ`` with ``δ = x ⊖ x̄`` per slot (``Log(x̄⁻¹x)`` for groups). Those factors
   are dropped.
2. shifts the window by one slot and appends the new state (initial guess) and the
   step's factor data (a motion factor to the previous state, unary factors, up to
   ``M`` loop factors to older states still in the window; loop factors whose other end
   was marginalised are dropped, as in GTSAM, whose fixed-lag smoothers remove the
   factors of marginalised variables);
3. solves the window by Gauss–Newton (Cholesky of the normal equations: block
   tridiagonal, ``O(K·d³)``, without loop factors; dense, ``n = K·d``, with them; ``d``
   the tangent size of one state) until the largest change of the estimate (tangent
   components) is below ``tol``.

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

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax.flatten_util import ravel_pytree

from ..lie import manifold
from ..lie._base import small_matmul

Array = jax.Array
PyTree = Any


def _stack(x: PyTree, k: int) -> PyTree:
    return jax.tree.map(lambda a: jnp.broadcast_to(jnp.asarray(a)[None], (k, *jnp.shape(a))), x)


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
    the last update.
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
    motion: Callable[..., Array] = eqx.field(static=True)
    unary: Callable[..., Array] | None = eqx.field(static=True)
    loop: Callable[..., Array] | None = eqx.field(static=True)
    window: int = eqx.field(static=True)
    max_iterations: int = eqx.field(static=True)
    tol: float = eqx.field(static=True)
    exact_prior_jacobian: bool = eqx.field(static=True)
    first_estimate: bool = eqx.field(static=True)
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
        """
        if not callable(motion):
            raise TypeError("FixedLagSmoother(motion): expected a callable")
        for name, fn in (("unary", unary), ("loop", loop)):
            if fn is not None and not callable(fn):
                raise TypeError(f"FixedLagSmoother({name}): expected a callable or None")
        if not isinstance(window, int) or window < 2:
            raise ValueError(f"FixedLagSmoother(window): expected an int >= 2, got {window!r}")
        if not isinstance(max_loops, int) or max_loops < 0:
            raise ValueError(
                f"FixedLagSmoother(max_loops): expected an int >= 0, got {max_loops!r}"
            )
        if max_loops > 0 and (loop is None or loop_data is None):
            raise ValueError("FixedLagSmoother(max_loops > 0): needs loop and loop_data")
        if not isinstance(max_iterations, int) or max_iterations < 1:
            raise ValueError(
                f"FixedLagSmoother(max_iterations): expected an int >= 1, got {max_iterations!r}"
            )
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
        self.motion, self.unary, self.loop = motion, unary, loop
        self.window, self.max_iterations = window, max_iterations
        eps = jnp.finfo(dtype).eps
        self.tol = float(tol) if tol is not None else (1e-8 if eps < 1e-10 else 1e-4)
        self.exact_prior_jacobian = bool(exact_prior_jacobian)
        self.first_estimate = bool(first_estimate)

    # ------------------------------------------------------------------ helpers
    @property
    def tangent_dim(self) -> int:
        """Tangent size d of one state."""
        return manifold.tangent_size(_take(self.states, 0))

    @property
    def valid(self) -> Array:
        """(K,) bool: slots holding a state (the last ``min(count, K)``)."""
        return jnp.arange(self.window) >= self.window - self.count

    def latest(self) -> PyTree:
        """The newest state estimate."""
        return _take(self.states, self.window - 1)

    def linearization_point(self) -> PyTree:
        """(K, ...) where the factors are linearised: the prior's point for the states in
        the prior (with first-estimate Jacobians), the estimate elsewhere."""
        return _where(self.frozen, self.prior_point, self.states)

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
                return fn(self._plus(a, e[:d], lin), self._plus(b, e[d:], lin), dat)

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

    def _unary_terms(self, x: PyTree) -> tuple[Array, Array]:
        """Residuals (m, r) and Jacobians (m, r, d) of the unary factors of stacked x."""
        unary, d = self.unary, self.tangent_dim

        def one(xs, dat):
            def f(e):
                return unary(self._plus(xs, e, "retract_linear"), dat)

            z = jnp.zeros(d, self.prior_grad.dtype)
            return f(z), jax.jacfwd(f)(z)

        return jax.vmap(one)(x, _take(self.data, jnp.arange(jax.tree.leaves(x)[0].shape[0])))

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

    def _chain_system(self, x: PyTree) -> tuple[Array, Array, Array]:
        """Block-tridiagonal Gauss–Newton system at x: diagonal blocks (K, d, d), upper
        blocks (K−1, d, d) (slot s, s+1) and gradient (K, d)."""
        k, d = self.window, self.tangent_dim
        valid = self.valid
        slots = jnp.arange(k)
        a, b = slots[:-1], slots[1:]
        r, ja, jb = self._pair_terms(self.motion, _take(x, a), _take(x, b), _take(self.data, b), d)
        mask = (valid[a] & valid[b])[:, None, None]
        ja, jb = jnp.where(mask, ja, 0.0), jnp.where(mask, jb, 0.0)
        r = jnp.where(mask[:, :, 0], r, 0.0)
        diag = jnp.zeros((k, d, d), r.dtype)
        diag = diag.at[:-1].add(small_matmul(ja.mT, ja))
        diag = diag.at[1:].add(small_matmul(jb.mT, jb))
        up = small_matmul(ja.mT, jb)
        g = jnp.zeros((k, d), r.dtype)
        g = g.at[:-1].add(jnp.einsum("mra,mr->ma", ja, r))
        g = g.at[1:].add(jnp.einsum("mra,mr->ma", jb, r))
        if self.unary is not None:
            ru, ju = self._unary_terms(x)
            ju = jnp.where(valid[:, None, None], ju, 0.0)
            ru = jnp.where(valid[:, None], ru, 0.0)
            diag = diag + small_matmul(ju.mT, ju)
            g = g + jnp.einsum("mra,mr->ma", ju, ru)
        hp, gp, _ = self._prior_terms(_take(x, 0), _take(self.prior_point, 0))
        diag = diag.at[0].add(hp)
        g = g.at[0].add(gp)
        return diag, up, g

    @staticmethod
    def _solve_chain(diag: Array, up: Array, rhs: Array) -> Array:
        """Solve the SPD block-tridiagonal system (block Cholesky / Thomas), (K, d)."""

        def fwd(carry, inp):
            s_prev, y_prev = carry
            d_i, b_prev, r_i = inp
            cf = jsl.cho_factor(s_prev)
            s_i = d_i - b_prev.T @ jsl.cho_solve(cf, b_prev)
            y_i = r_i - b_prev.T @ jsl.cho_solve(cf, y_prev)
            return (s_i, y_i), (s_i, y_i)

        _, (ss, ys) = jax.lax.scan(fwd, (diag[0], rhs[0]), (diag[1:], up, rhs[1:]))
        ss = jnp.concatenate([diag[:1], ss])
        ys = jnp.concatenate([rhs[:1], ys])
        x_last = jsl.cho_solve(jsl.cho_factor(ss[-1]), ys[-1])

        def back(x_next, inp):
            s_i, y_i, b_i = inp
            x_i = jsl.cho_solve(jsl.cho_factor(s_i), y_i - b_i @ x_next)
            return x_i, x_i

        _, xs = jax.lax.scan(back, x_last, (ss[:-1], ys[:-1], up), reverse=True)
        return jnp.concatenate([xs, x_last[None]])

    def _system(self, x: PyTree, touching_first: bool) -> tuple[Array, Array, Array]:
        """Gauss–Newton system (H (n, n), g (n,), cost) at ``x``; with
        ``touching_first`` only the factors touching slot 0 (and the prior)."""
        k, d = self.window, self.tangent_dim
        dtype = self.prior_grad.dtype
        valid = self.valid
        h = jnp.zeros((k, d, k, d), dtype)
        g = jnp.zeros((k, d), dtype)
        cost = jnp.zeros((), dtype)

        def add(h, g, cost, a, b, r, ja, jb, mask):
            mask = mask.astype(bool)
            r = jnp.where(mask[:, None], r, 0.0)
            ja = jnp.where(mask[:, None, None], ja, 0.0)
            jb = jnp.where(mask[:, None, None], jb, 0.0)
            h = h.at[a, :, a, :].add(small_matmul(ja.mT, ja))
            h = h.at[a, :, b, :].add(small_matmul(ja.mT, jb))
            h = h.at[b, :, a, :].add(small_matmul(jb.mT, ja))
            h = h.at[b, :, b, :].add(small_matmul(jb.mT, jb))
            g = g.at[a].add(jnp.einsum("mra,mr->ma", ja, r))
            g = g.at[b].add(jnp.einsum("mra,mr->ma", jb, r))
            return h, g, cost + 0.5 * jnp.sum(r * r)

        slots = jnp.arange(k)
        # motion factors (s-1, s), s = 1..K-1
        a, b = slots[:-1], slots[1:]
        r, ja, jb = self._pair_terms(self.motion, _take(x, a), _take(x, b), _take(self.data, b), d)
        mask = valid[a] & valid[b]
        if touching_first:
            mask = mask & (a == 0)
        h, g, cost = add(h, g, cost, a, b, r, ja, jb, mask)
        # unary factors
        if self.unary is not None:
            unary = self.unary

            def one(xs, dat):
                def f(e):
                    return unary(self._plus(xs, e, "retract_linear"), dat)

                z = jnp.zeros(d, dtype)
                return f(z), jax.jacfwd(f)(z)

            r, ju = jax.vmap(one)(x, self.data)
            mask = valid if not touching_first else valid & (slots == 0)
            h, g, cost = add(h, g, cost, slots, slots, r, ju, jnp.zeros_like(ju), mask)
        # loop factors (s - lag, s)
        m = self.loop_lag.shape[1]
        if self.loop is not None and m > 0:
            b = jnp.repeat(slots, m)
            lag = self.loop_lag.reshape(-1)
            a = b - lag
            ok = (a >= 0) & (lag >= 1) & self.loop_valid.reshape(-1)
            a = jnp.clip(a, 0, k - 1)
            ok = ok & valid[a] & valid[b]
            if touching_first:
                ok = ok & (a == 0)
            ld = jax.tree.map(lambda v: v.reshape(k * m, *v.shape[2:]), self.loop_data)
            r, ja, jb = self._pair_terms(self.loop, _take(x, a), _take(x, b), ld, d)
            h, g, cost = add(h, g, cost, a, b, r, ja, jb, ok)
        h = h.reshape(k * d, k * d)
        g = g.reshape(k * d)
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
        hp4 = pinfo.reshape(k, d, k, d)
        h = h + jnp.einsum("iab,iajc,jcd->ibjd", jac, hp4, jac).reshape(k * d, k * d)
        grad_p = (pinfo @ dv + pgrad).reshape(k, d)
        g = g + jnp.einsum("iab,ia->ib", jac, grad_p).reshape(-1)
        cost = cost + pgrad @ dv + 0.5 * dv @ (pinfo @ dv)
        return h, g, cost

    def _regularised(self, h: Array) -> Array:
        """Identity on the diagonal blocks of empty slots (their step is then zero)."""
        d = self.tangent_dim
        empty = jnp.repeat(~self.valid, d).astype(h.dtype)
        return h + jnp.diag(empty)

    def _optimize(self) -> FixedLagSmoother:
        k, d = self.window, self.tangent_dim

        def cond(c):
            _, it, done = c
            return (it < self.max_iterations) & ~done

        def body(c):
            x, it, _ = c
            y = _where(self.frozen, self.prior_point, x)
            if self.chain:
                diag, up, g = self._chain_system(y)
                empty = (~self.valid).astype(g.dtype)[:, None, None]
                diag = diag + empty * jnp.eye(d, dtype=g.dtype)
                step = self._solve_chain(diag, up, -g)
            else:
                h, g, _ = self._system(y, False)
                cf = jsl.cho_factor(self._regularised(h))
                step = -jsl.cho_solve(cf, g)
            ok = jnp.all(jnp.isfinite(step))
            step = jnp.where(ok, step, 0.0).reshape(k, d)
            x_new = _where(ok, jax.vmap(self._plus)(y, step), x)
            change = jax.vmap(self._minus)(x_new, x)
            done = ~ok | (jnp.max(jnp.abs(change)) < self.tol)
            return x_new, it + 1, done

        x, it, _ = jax.lax.while_loop(
            cond, body, (self.states, jnp.zeros((), jnp.int32), jnp.zeros((), bool))
        )
        return eqx.tree_at(lambda s: (s.states, s.iterations), self, (x, it))

    def _marginalize_first(self) -> tuple[Array, Array, Array]:
        """Prior on slots 1..K-1 (shifted to 0..K-2, last slot empty) after eliminating
        slot 0 at the linearisation point, and the (K,) slots it couples (shifted)."""
        k, d = self.window, self.tangent_dim
        if self.chain:
            return self._marginalize_chain()
        h, g, _ = self._system(self.linearization_point(), True)
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
        """Chain case of :meth:`_marginalize_first`: the new prior lives on slot 1."""
        d = self.tangent_dim
        y = self.linearization_point()
        pair = jnp.array([0, 1])
        x01 = _take(y, pair)
        r, ja, jb = self._pair_terms(
            self.motion, _take(x01, pair[:1]), _take(x01, pair[1:]), _take(self.data, pair[1:]), d
        )
        r, ja, jb = r[0], ja[0], jb[0]
        h00, g0, _ = self._prior_terms(_take(y, 0), _take(self.prior_point, 0))
        h00 = h00 + ja.T @ ja
        g0 = g0 + ja.T @ r
        if self.unary is not None:
            ru, ju = self._unary_terms(_take(y, pair[:1]))
            h00 = h00 + ju[0].T @ ju[0]
            g0 = g0 + ju[0].T @ ru[0]
        h01, h11, g1 = ja.T @ jb, jb.T @ jb, jb.T @ r
        cf = jsl.cho_factor(h00)
        info = h11 - h01.T @ jsl.cho_solve(cf, h01)
        grad = g1 - h01.T @ jsl.cho_solve(cf, g0)
        coupled = jnp.zeros((self.window,), bool).at[0].set(True)
        return 0.5 * (info + info.T), grad, coupled

    # ------------------------------------------------------------------ public
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
        if jax.tree.structure(guess) != jax.tree.structure(_take(self.states, 0)):
            raise TypeError(
                "FixedLagSmoother.update(guess): expected the structure of the example state"
            )
        if jax.tree.structure(data) != jax.tree.structure(_take(self.data, 0)):
            raise TypeError(
                "FixedLagSmoother.update(data): expected the structure of the example data"
            )
        for a, b in zip(
            jax.tree.leaves(guess), jax.tree.leaves(_take(self.states, 0)), strict=True
        ):
            if jnp.shape(a) != jnp.shape(b):
                raise ValueError(
                    f"FixedLagSmoother.update(guess): leaf of shape "
                    f"{jnp.shape(a)}, expected {jnp.shape(b)}"
                )
        m = self.loop_lag.shape[1]
        if m:
            if loop_lag is None or loop_valid is None or loop_data is None:
                raise ValueError(
                    "FixedLagSmoother.update: this smoother has max_loops > 0; "
                    "pass loop_lag, loop_valid and loop_data"
                )
            lag = jnp.asarray(loop_lag, jnp.int32)
            lv = jnp.asarray(loop_valid, bool)
            if lag.shape != (m,) or lv.shape != (m,):
                raise ValueError(
                    f"FixedLagSmoother.update(loop_lag, loop_valid): expected "
                    f"shape ({m},), got {lag.shape} and {lv.shape}"
                )
        guess = eqx.error_if(
            guess,
            ~jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in jax.tree.leaves(guess)])),
            "FixedLagSmoother.update(guess): non-finite values",
        )
        full = self.valid[0]
        info_m, grad_m, coupled = self._marginalize_first()
        if self.chain:  # before the first marginalisation the prior is empty
            info_s, grad_s = self.prior_info, self.prior_grad
        else:
            dd = (k - 1) * d
            info_s = jnp.zeros_like(self.prior_info).at[:dd, :dd].set(self.prior_info[d:, d:])
            grad_s = jnp.zeros_like(self.prior_grad).at[:dd].set(self.prior_grad[d:])
        info = jnp.where(full, info_m, info_s)
        grad = jnp.where(full, grad_m, grad_s)
        # a new prior is anchored at the linearisation point; else unchanged
        point = _shift_in(_where(full, self.linearization_point(), self.prior_point), guess)
        frozen = _shift_in(self.frozen, jnp.zeros((), bool))
        if self.first_estimate:
            frozen = jnp.where(full, coupled, frozen)
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
        return new._optimize()

    def information(self) -> Array:
        """(n, n) Gauss–Newton information of the window at the current estimate
        (empty slots: identity blocks), tangent layout slot-major."""
        h, _, _ = self._system(self.linearization_point(), False)
        return self._regularised(h)

    def cost(self) -> Array:
        """Window cost ``½Σ‖r‖² + prior`` at the current estimate."""
        return self._system(self.states, False)[2]

    def marginal_covariances(self) -> Array:
        """(K, d, d) marginal covariances of the window states (blocks of the inverse
        window information, in each state's right tangent chart; NaN for empty slots)."""
        k, d = self.window, self.tangent_dim
        h = self.information()
        cov = jsl.cho_solve(jsl.cho_factor(h), jnp.eye(k * d, dtype=h.dtype))
        blocks = cov.reshape(k, d, k, d)[jnp.arange(k), :, jnp.arange(k), :]
        return jnp.where(self.valid[:, None, None], blocks, jnp.nan)
