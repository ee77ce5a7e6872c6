"""Trajectory costs ``J = Σ_t ℓ(x_t, u_t, t) + ℓ_T(x_T)``.

:class:`QuadraticCost` is PyPose's convention: ``ℓ = ½ τᵀ Q_t τ + p_tᵀ τ`` with
``τ = [x; u]`` (state first), plus an optional terminal ``½ xᵀ Q_T x + p_Tᵀ x`` (PyPose's
MPC has none). Any other cost: subclass :class:`Cost` or wrap functions with
:class:`FunctionCost`; second-order expansions then come from autodiff.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from ..dynamics._checks import as_array, check_psd, start_step, step_index, step_window

Array = jax.Array


class Cost(eqx.Module):
    """Base cost. Implement :meth:`stage` (scalar for one step) and optionally
    :meth:`terminal`. Array fields are differentiable parameters."""

    @abc.abstractmethod
    def stage(self, x: Array, u: Array, t: Any) -> Array:
        """Scalar stage cost ℓ(x, u, t) for one state (n,) and input (m,) at step ``t``."""

    def terminal(self, x: Array) -> Array:
        """Scalar terminal cost ℓ_T(x) of the final state (n,) (default 0)."""
        return jnp.zeros((), x.dtype)

    def quadratize(self, x: Array, u: Array, t: Any) -> tuple[Array, Array]:
        """Hessian (n+m, n+m) and gradient (n+m,) of ``stage`` w.r.t. ``τ = [x; u]``."""
        n = x.shape[-1]
        fn = lambda tau: self.stage(tau[:n], tau[n:], t)
        tau = jnp.concatenate([x, u])
        return jax.hessian(fn)(tau), jax.grad(fn)(tau)

    def quadratize_terminal(self, x: Array) -> tuple[Array, Array]:
        """Hessian (n, n) and gradient (n,) of ``terminal``."""
        return jax.hessian(self.terminal)(x), jax.grad(self.terminal)(x)

    def total(self, xs: Array, us: Array, t0: Any = 0) -> Array:
        """``Σ_t ℓ(x_t, u_t, t0 + t) + ℓ_T(x_T)`` for xs (T+1, n), us (T, m)."""
        ts = jnp.asarray(t0) + jnp.arange(us.shape[0])
        stages = jax.vmap(self.stage)(xs[:-1], us, ts)
        return jnp.sum(stages) + self.terminal(xs[-1])


class FunctionCost(Cost):
    """Cost from plain functions ``stage_fn(x, u, t)`` and ``terminal_fn(x)`` (optional).
    Use an equinox Module as the function to make its arrays differentiable."""

    stage_fn: Callable[[Array, Array, Any], Array]
    terminal_fn: Callable[[Array], Array] | None = None

    def stage(self, x: Array, u: Array, t: Any) -> Array:
        return self.stage_fn(x, u, t)

    def terminal(self, x: Array) -> Array:
        if self.terminal_fn is None:
            return jnp.zeros((), x.dtype)
        return self.terminal_fn(x)


class QuadraticCost(Cost):
    """``ℓ_t = ½ τᵀ Q_t τ + p_tᵀ τ`` (τ = [x; u]) and ``ℓ_T = ½ xᵀ Q_T x + p_Tᵀ x``.

    ``Q`` (k, k) or time-varying (T, k, k), ``p`` (k,) or (T, k) with ``k = n + m``;
    ``QT`` (n, n) and ``pT`` (n,) optional (zero). A time-varying cost at step ``t``
    uses ``Q[t]``/``p[t]`` (a ``t`` outside 0 … T − 1 or fractional raises; solvers raise
    when the horizon needs more steps than it has). Only the symmetric parts of ``Q`` and
    ``QT`` matter (the quadratic forms are symmetrised); they must be positive
    semi-definite: concrete values are checked here (ValueError naming the
    argument); traced values are not, and a solve on an indefinite problem reports a
    non-finite status instead."""

    Q: Array
    p: Array
    QT: Array | None = None
    pT: Array | None = None  # noqa: N815 - math notation (p_T)

    def __init__(self, Q: Any, p: Any = None, QT: Any = None, pT: Any = None):
        Q = as_array(Q, "Q", (2, 3))
        if Q.shape[-1] != Q.shape[-2]:
            raise ValueError(
                f"Q: expected square (k, k) or (T, k, k) with k = n + m, got {tuple(Q.shape)}"
            )
        check_psd(Q, "Q", symmetric=False)
        k = Q.shape[-1]
        p = jnp.zeros(k, Q.dtype) if p is None else as_array(p, "p", (1, 2))
        if p.shape[-1] != k:
            raise ValueError(
                f"p: expected last dimension {k} (= Q.shape[-1] = n + m), "
                f"got shape {tuple(p.shape)}"
            )
        if Q.ndim == 3 and p.ndim == 2 and Q.shape[0] != p.shape[0]:
            raise ValueError(f"p: expected {Q.shape[0]} time steps like Q, got {p.shape[0]}")
        if QT is not None:
            QT = as_array(QT, "QT", 2)
            check_psd(QT, "QT", symmetric=False)
        if pT is not None:
            pT = as_array(pT, "pT", 1)
            if QT is not None and pT.shape[0] != QT.shape[0]:
                raise ValueError(
                    f"pT: expected shape ({QT.shape[0]},) like QT, got {tuple(pT.shape)}"
                )
        self.Q, self.p, self.QT, self.pT = Q, p, QT, pT

    @classmethod
    def tracking(cls, Q: Any, tau_ref: Any, QT: Any = None, x_ref: Any = None) -> QuadraticCost:
        """``½ (τ − τ_ref)ᵀ Q (τ − τ_ref)`` (+ terminal ``½ (x − x_ref)ᵀ Q_T (x − x_ref)``),
        up to a constant: ``p = −sym(Q) τ_ref`` (only Q's symmetric part counts, as in
        the stage cost)."""
        Q = as_array(Q, "Q", (2, 3))
        tau_ref = as_array(tau_ref, "tau_ref", (1, 2))
        p = -jnp.einsum("...ij,...j->...i", _sym(Q), tau_ref)
        pT = None
        if QT is not None and x_ref is not None:
            pT = -_sym(as_array(QT, "QT", 2)) @ as_array(x_ref, "x_ref", 1)
        return cls(Q, p, QT, pT)

    @property
    def size(self) -> int:
        """``k = n + m``."""
        return self.Q.shape[-1]

    @property
    def time_varying(self) -> int | None:
        """Number of time steps of Q/p if time-varying, else None."""
        if self.Q.ndim == 3:
            return self.Q.shape[0]
        if self.p.ndim == 2:
            return self.p.shape[0]
        return None

    def _at(self, t: Any) -> tuple[Array, Array]:
        tv = self.time_varying
        t = step_index(t, steps=tv, whose="cost's") if tv is not None else t
        Q = self.Q[t] if self.Q.ndim == 3 else self.Q
        p = self.p[t] if self.p.ndim == 2 else self.p
        return _sym(Q), p

    def stage(self, x: Array, u: Array, t: Any) -> Array:
        tau = jnp.concatenate([x, u])
        Q, p = self._at(t)
        return 0.5 * tau @ (Q @ tau) + p @ tau

    def terminal(self, x: Array) -> Array:
        out = jnp.zeros((), x.dtype)
        if self.QT is not None:
            out = out + 0.5 * x @ (self.QT @ x)
        if self.pT is not None:
            out = out + self.pT @ x
        return out

    def quadratize(self, x: Array, u: Array, t: Any) -> tuple[Array, Array]:
        tau = jnp.concatenate([x, u])
        Q, p = self._at(t)
        return Q, Q @ tau + p

    def quadratize_terminal(self, x: Array) -> tuple[Array, Array]:
        n = x.shape[-1]
        QT = jnp.zeros((n, n), x.dtype) if self.QT is None else _sym(self.QT)
        g = QT @ x
        if self.pT is not None:
            g = g + self.pT
        return QT, g

    def stacked(self, horizon: int, n: int, t0: Any = 0
                ) -> tuple[Array, Array, Array, Array]:
        """``(C (T, k, k), c (T, k), CT (n, n), cT (n,))`` for the LQR recursion over the
        steps ``t0`` … ``t0 + T − 1`` (``t0`` may be traced; steps outside a time-varying
        cost's raise, never clamp)."""
        t0 = start_step(t0)
        k = self.size
        Qs = _sym(self.Q)
        C = (step_window(Qs, t0, horizon, "cost's") if Qs.ndim == 3
             else jnp.broadcast_to(Qs, (horizon, k, k)))
        c = (step_window(self.p, t0, horizon, "cost's") if self.p.ndim == 2
             else jnp.broadcast_to(self.p, (horizon, k)))
        dt = self.Q.dtype
        CT = jnp.zeros((n, n), dt) if self.QT is None else _sym(self.QT)
        cT = jnp.zeros((n,), dt) if self.pT is None else self.pT
        if CT.shape != (n, n):
            raise ValueError(f"QT: expected shape ({n}, {n}) (n states), got {tuple(CT.shape)}")
        if cT.shape != (n,):
            raise ValueError(f"pT: expected shape ({n},) (n states), got {tuple(cT.shape)}")
        return C, c, CT, cT


def _sym(M: Array) -> Array:
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))
