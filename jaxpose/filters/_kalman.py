"""What the Gaussian filters share: the fields every filter holds (``model``, ``Q``, ``R``,
``skip_nonfinite``), the error-state correction of the EKF and UKF updates, and their
``step``/``run`` drivers (a ``lax.scan`` over predict-then-update)."""

from __future__ import annotations

import abc
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._dtypes import keep_dtypes
from .._precision import full_precision
from ..dynamics._system import System
from ..dynamics._tangent import TangentSpace, tangent_space
from ._common import (
    FilterResult,
    as_state,
    check_cov,
    check_sequence,
    finite_tree,
    innovation_ok,
    model_and_noise,
    noise_checked,
    select_tree,
    symmetrize,
)

Array = jax.Array


class NoisyModelFilter(eqx.Module):
    """Fields of every filter: the :class:`~jaxpose.dynamics.System` ``model``, process
    noise ``Q`` (k, k) in the state's tangent coordinates, measurement noise ``R`` (p, p)
    and whether non-finite measurements are skipped (``skip_nonfinite``)."""

    model: System
    Q: Array
    R: Array
    skip_nonfinite: bool = eqx.field(static=True, default=False)

    def __init__(self, model: System, Q: Any, R: Any, skip_nonfinite: bool = False):
        self.model, self.Q, self.R = model_and_noise(model, Q, R)
        self.skip_nonfinite = bool(skip_nonfinite)

    def _noise_checked(self, *, once: bool) -> NoisyModelFilter:
        """This filter with ``Q`` and ``R`` checked again (``eqx.tree_at`` can put in a
        value the constructor refuses): where known, and with ``once`` (a whole run) also
        in the compiled program, as a run's ``P0`` is."""
        Q, R = noise_checked(self.Q, self.R, once=once)
        return eqx.tree_at(lambda f: (f.Q, f.R), self, (Q, R))


class KalmanFilter(NoisyModelFilter):
    """Base of :class:`~jaxpose.filters.EKF` and :class:`~jaxpose.filters.UKF`: subclasses
    implement :meth:`predict` and ``_update`` (returning ``(x, P, used)``)."""

    @abc.abstractmethod
    def predict(self, x: Any, P: Array, u: Array, t: Any = 0) -> tuple[Any, Array]:
        """Predicted ``(x⁻, P⁻)`` through ``f(·, u, t)``; P (k, k) in tangent coordinates."""

    @abc.abstractmethod
    def _update(self, x: Any, P: Array, y: Any, u: Array, t: Any) -> tuple[Any, Array, Array]:
        """:meth:`update` and whether the measurement was used."""

    @full_precision
    def update(self, x: Any, P: Array, y: Any, u: Array, t: Any = 0) -> tuple[Any, Array]:
        """Correct ``(x, P)`` with a measurement ``y`` (p,) of ``h(x, u, t)``; returns the
        posterior estimate and covariance (k, k). ``P`` is checked as in :meth:`step`."""
        return self._update(x, P, y, u, t)[:2]

    def step(self, x: Any, P: Array, y: Any, u: Array, t: Any = 0) -> tuple[Any, Array]:
        """Predict with ``u`` then update with ``y``; also ``filter(x, P, y, u, t)``.
        ``P`` is checked for its shape always and for its values (symmetric positive
        semi-definite) where they are known (not under ``jit``, unlike ``run``'s ``P0``),
        and so are ``Q`` and ``R``.
        Compiled on first call (``eqx.filter_jit``; ``t`` is passed as an array, so a loop
        over time steps reuses one program)."""
        x = as_state(x)
        P = check_cov(P, tangent_space(x).dim, "P")  # eager: its values are checked
        return _compiled_step(self._noise_checked(once=False), x, P, y, u, jnp.asarray(t))

    def _step(self, x: Any, P: Array, y: Any, u: Array, t: Any) -> tuple[Any, Array, Array]:
        xp, Pp = self.predict(x, P, u, t)
        return self._update(xp, Pp, y, u, t)

    __call__ = step

    def run(self, x0: Any, P0: Any, ys: Any, us: Array, t0: Any = 0) -> FilterResult:
        """Filter a sequence with ``lax.scan``: ``ys`` (N, p), ``us`` (N, m); returns the
        N posterior estimates (after each update). Sizes are checked at trace time:
        ``P0`` against ``x0``, ``ys`` against ``h(x0)`` and ``R``, ``us`` against ``ys``.
        Compiled on first call (``eqx.filter_jit``): new arrays of the same shapes reuse
        the program."""
        x0 = as_state(x0, "x0")
        P0 = check_cov(P0, tangent_space(x0).dim, "P0", once=True)
        return _compiled_run(self._noise_checked(once=True), x0, P0, ys, us, jnp.asarray(t0))

    def _run(self, x0: Any, P0: Array, ys: Any, us: Array, t0: Array) -> FilterResult:
        us = check_sequence(self.model, self.R, x0, ys, us, t0)
        n_y = jax.tree.leaves(ys)[0].shape[0]
        ts = jnp.asarray(t0) + jnp.arange(n_y)

        def body(carry: tuple[Any, Array], inp: tuple[Any, Array, Array]):
            x, P = carry
            y, u, t = inp
            new_x, new_P, used = self._step(x, P, y, u, t)
            # float64 model/noise data: the estimate keeps the dtypes of (x0, P0)
            x, P = keep_dtypes((new_x, new_P), (x, P))
            return (x, P), (x, P, used & finite_tree(x, P))

        _, (xs, Ps, ok) = jax.lax.scan(body, (x0, P0), (ys, us, ts))
        return FilterResult(xs, Ps, ok)

    def _correct(
        self,
        ts: TangentSpace,
        x: Any,
        P: Array,
        P_new: Array,
        K: Array,
        L: Array,
        r: Array,
        y_ok: Array,
    ) -> tuple[Any, Array, Array]:
        """Error-state correction ``x ⊕ K r`` with the posterior covariance ``P_new``;
        with ``skip_nonfinite``, a measurement that is not finite (``y_ok`` False) or whose
        normalised innovation overflows (``S = L Lᵀ``) leaves ``(x, P)`` unchanged.
        Returns ``(x, P, used)``."""
        use = y_ok & innovation_ok(L, r) if self.skip_nonfinite else y_ok
        x_new = ts.plus(x, K @ jnp.where(use, r, 0.0))
        if self.skip_nonfinite:
            x_new, P_new = select_tree(use, (x_new, P_new), (x, P))
        return x_new, symmetrize(P_new), use


@eqx.filter_jit
@full_precision
def _compiled_step(filt: KalmanFilter, x: Any, P: Array, y: Any, u: Array,
                   t: Array) -> tuple[Any, Array]:
    return filt._step(x, P, y, u, t)[:2]


@eqx.filter_jit
@full_precision
def _compiled_run(filt: KalmanFilter, x0: Any, P0: Any, ys: Any, us: Array,
                  t0: Array) -> FilterResult:
    return filt._run(x0, P0, ys, us, t0)


def safe_measurement(y: Any, y_hat: Any, skip: bool) -> tuple[Any, Array]:
    """With ``skip``: ``(y, finite)`` where y is finite, else ``(y_hat, False)`` — the
    replaced value keeps NaN out of the (discarded) update and of its derivatives."""
    if not skip:
        return y, jnp.asarray(True)
    ok = finite_tree(y)
    return select_tree(ok, y, y_hat), ok
