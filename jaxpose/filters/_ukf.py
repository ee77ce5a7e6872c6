"""Unscented Kalman filter with Merwe's scaled sigma points (van der Merwe 2004).

``λ = α²(k + κ) − k``; sigma points ``x``, ``x ⊕ ±col_i(√((k+λ)P))`` (lower Cholesky
columns; for a positive *semi*-definite P, e.g. ``P0 = 0``, the factor's null directions
are zero columns: a semidefinite Cholesky, exact for PD and PSD P); weights
``Wm_0 = λ/(k+λ)``, ``Wc_0 = Wm_0 + 1 − α² + β``,
``W_i = 1/(2(k+λ))``. Same model and step convention as :class:`~jaxpose.filters.EKF`.
For group states the sigma points are ``x ⊕ s_i`` and means are taken in the tangent
space of the propagated central point (one Gauss–Newton step of the Fréchet mean, as in
UKF-M, Brossard et al. 2020). Sigma points are redrawn from the predicted Gaussian for
the update, so on linear-Gaussian models the UKF equals the Kalman filter.
``skip_nonfinite`` as in :mod:`~jaxpose.filters._ekf`. Without it, a finite but absurd
measurement (1e200) moves the state to ~1e199, where the sigma-point deviations (rounding
at that magnitude) square to overflow: the covariance becomes NaN for the rest of the run
(the EKF's does not, being independent of the state for linear models); with it, such a
measurement is skipped.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._precision import full_precision
from ..dynamics._system import System
from ..dynamics._tangent import tangent_space
from ._common import (
    as_state,
    check_cov,
    check_measurement,
    check_noise_dim,
    kalman_gain,
    psd_cholesky,
    symmetrize,
)
from ._kalman import KalmanFilter, safe_measurement

Array = jax.Array


def merwe_weights(
    k: int, alpha: float, beta: float, kappa: float, dtype: Any
) -> tuple[Array, Array, Array]:
    """``(Wm, Wc, scale)`` for ``2k+1`` sigma points; ``scale = k + λ``."""
    lam = alpha**2 * (k + kappa) - k
    c = k + lam
    if c <= 0:
        raise ValueError(
            f"alpha, kappa: need α²(k + κ) > 0 for k = {k}, got α = {alpha}, κ = {kappa}"
        )
    wi = jnp.full((2 * k,), 0.5 / c, dtype)
    wm = jnp.concatenate([jnp.array([lam / c], dtype), wi])
    wc = jnp.concatenate([jnp.array([lam / c + 1.0 - alpha**2 + beta], dtype), wi])
    return wm, wc, jnp.asarray(c, dtype)


class UKF(KalmanFilter):
    """``UKF(model, Q, R, alpha=1.0, beta=2.0, kappa=0.0, skip_nonfinite=False)``; ``Q``
    (k, k), ``R`` (p, p); ``P`` may be positive semi-definite (``P0 = 0``).

    Defaults α = 1, β = 2, κ = 0 keep all weights non-negative except none (Wm_0 = 0);
    small α (e.g. 1e-3) gives large negative central weights and loses digits."""

    alpha: float = eqx.field(static=True, default=1.0)
    beta: float = eqx.field(static=True, default=2.0)
    kappa: float = eqx.field(static=True, default=0.0)

    def __init__(
        self,
        model: System,
        Q: Any,
        R: Any,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        skip_nonfinite: bool = False,
    ):
        super().__init__(model, Q, R, skip_nonfinite)
        if not alpha > 0:
            raise ValueError(f"alpha: expected > 0, got {alpha}")
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), float(kappa)

    def sigma_points(self, x: Any, P: Array) -> tuple[Any, Array, Array, Array]:
        """Stacked sigma points (2k+1, …), their tangent offsets (2k+1, k), Wm, Wc."""
        ts = tangent_space(x)
        wm, wc, c = merwe_weights(ts.dim, self.alpha, self.beta, self.kappa, P.dtype)
        L = psd_cholesky(c * P)
        offs = jnp.concatenate([jnp.zeros((1, ts.dim), P.dtype), L.T, -L.T], 0)
        pts = jax.vmap(lambda d: ts.plus(x, d))(offs)
        return pts, offs, wm, wc

    @full_precision
    def predict(self, x: Any, P: Array, u: Array, t: Any = 0) -> tuple[Any, Array]:
        """Propagate the sigma points through ``f(·, u, t)``: predicted mean and ``P⁻`` (k, k) + Q.

        ``x`` is an array (n,) or a Lie group element; ``P`` (k, k) in its tangent coordinates
        (checked as in :meth:`step`).
        """
        x = as_state(x)
        ts = tangent_space(x)
        P = check_cov(P, ts.dim, "P")
        check_noise_dim(self.Q, ts.dim, "Q", "state tangent size")
        pts, _, wm, wc = self.sigma_points(x, P)
        prop = jax.vmap(lambda s: self.model.state_transition(s, u, t))(pts)
        mean, dev = _mean(prop, wm)
        Pp = (wc[:, None] * dev).T @ dev + self.Q
        return mean, symmetrize(Pp)

    def _update(self, x: Any, P: Array, y: Any, u: Array, t: Any) -> tuple[Any, Array, Array]:
        x = as_state(x)
        ts = tangent_space(x)
        P = check_cov(P, ts.dim, "P")
        pts, offs, wm, wc = self.sigma_points(x, P)
        obs = jax.vmap(lambda s: self.model.observation(s, u, t))(pts)
        ymean, ydev = _mean(obs, wm)
        p = ydev.shape[-1]
        check_noise_dim(self.R, p, "R", f"measurement noise: h(x) gives {p} values")
        check_measurement(y, ymean, self.R)
        y, y_ok = safe_measurement(y, ymean, self.skip_nonfinite)
        Pyy = (wc[:, None] * ydev).T @ ydev + self.R
        Pxy = (wc[:, None] * offs).T @ ydev
        K, L = kalman_gain(Pxy, Pyy)
        r = tangent_space(ymean).minus(y, ymean)
        # P − K·Pyy·Kᵀ as Σ Wc·eᵢeᵢᵀ + K·R·Kᵀ with eᵢ = sᵢ − K·yᵢ (equal, as K·Pyy = Pxy): a
        # sum of outer products, the UKF's Joseph form. The difference of two matrices of
        # P's size lost float32 accuracy in proportion to P/R (P 2e-3 off at P/R = 1e4)
        e = offs - ydev @ K.T
        Pk = (wc[:, None] * e).T @ e + K @ self.R @ K.T
        return self._correct(ts, x, P, Pk, K, L, r, y_ok)


def _mean(pts: Any, wm: Array) -> tuple[Any, Array]:
    """Weighted mean of stacked points and the deviations (2k+1, d) from it."""
    first = jax.tree.map(lambda a: a[0], pts)
    ts = tangent_space(first)
    if ts.euclidean:
        mean = jnp.einsum("i,i...->...", wm, pts)
        return mean, pts - mean
    local = jax.vmap(lambda p: ts.minus(p, first))(pts)
    mean = ts.plus(first, wm @ local)
    dev = jax.vmap(lambda p: ts.minus(p, mean))(pts)
    return mean, dev
