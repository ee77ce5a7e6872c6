"""Extended Kalman filter on vector or Lie-group states.

Model (a :class:`~jaxpose.dynamics.System`)::

    x_{k+1} = f(x_k, u_k, t) ⊕ w,  w ~ N(0, Q)        y = h(x_{k+1}, u_k, t) + v,  v ~ N(0, R)

One :meth:`EKF.step` predicts through ``f`` and corrects with the measurement ``y`` of the
predicted state (the textbook EKF; PyPose's ``EKF.forward`` evaluates ``h`` at the previous
state instead — docs/pypose-migration.md compares the two). For group states
(``X ⊕ δ = X·Exp(δ)``) the covariance lives in the right tangent space:
``F = ∂[f(x ⊕ δ) ⊖ f(x)]/∂δ``, the update is ``x⁺ = x⁻ ⊕ K r`` (error-state form).
Covariance updates use the Joseph form ``(I − KH) P (I − KH)ᵀ + K R Kᵀ``
(``joseph=False``: ``P − K S Kᵀ``, symmetrised).

Non-finite measurements (all filters, ``skip_nonfinite``): by default (``False``) a NaN/inf
measurement is used like any other, so NaN reaches the estimate and stays there for the
rest of a run (``FilterResult.ok`` False from that step on). With ``skip_nonfinite=True``
a measurement that is not finite, or whose normalised innovation ``rᵀS⁻¹r`` overflows (an
innovation beyond ~1e154 standard deviations in float64, e.g. a value of 1e200: nothing of
it survives in floating point), is skipped: the step returns the prediction and ``ok`` is
False for that step only.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from .._precision import full_precision
from ..dynamics._system import System
from ..dynamics._tangent import tangent_jacobian, tangent_space
from ._common import (
    as_state,
    check_cov,
    check_measurement,
    check_noise_dim,
    kalman_gain,
    symmetrize,
)
from ._kalman import KalmanFilter, safe_measurement

Array = jax.Array


class EKF(KalmanFilter):
    """``EKF(model, Q, R, joseph=True, skip_nonfinite=False)``; ``Q`` (k, k) process noise
    in the state's tangent coordinates (k = n for vectors), ``R`` (p, p) measurement noise
    (PD). ``skip_nonfinite``: skip (predict only) a non-finite measurement or one whose
    normalised innovation overflows (see the module docstring)."""

    joseph: bool = eqx.field(static=True, default=True)

    def __init__(
        self, model: System, Q: Any, R: Any, joseph: bool = True, skip_nonfinite: bool = False
    ):
        super().__init__(model, Q, R, skip_nonfinite)
        self.joseph = joseph

    @full_precision
    def predict(self, x: Any, P: Array, u: Array, t: Any = 0) -> tuple[Any, Array]:
        """``x⁻ = f(x, u, t)``, ``P⁻ = F P Fᵀ + Q`` (``P`` checked as in :meth:`step`)."""
        x = as_state(x)
        ts = tangent_space(x)
        P = check_cov(P, ts.dim, "P")
        check_noise_dim(self.Q, ts.dim, "Q", "state tangent size")
        xp, F = tangent_jacobian(lambda s: self.model.state_transition(s, u, t), x, ts, ts)
        return xp, symmetrize(F @ P @ F.T + self.Q)

    def _update(self, x: Any, P: Array, y: Any, u: Array, t: Any) -> tuple[Any, Array, Array]:
        """:meth:`update` and whether the measurement was used."""
        x = as_state(x)
        ts = tangent_space(x)
        P = check_cov(P, ts.dim, "P")
        yh = self.model.observation(x, u, t)
        ys = tangent_space(yh)
        check_noise_dim(self.R, ys.dim, "R", f"measurement noise: h(x) gives {ys.dim} values")
        check_measurement(y, yh, self.R)
        _, H = tangent_jacobian(lambda s: self.model.observation(s, u, t), x, ts, ys)
        y, y_ok = safe_measurement(y, yh, self.skip_nonfinite)
        r = ys.minus(y, yh)
        PHt = P @ H.T
        S = H @ PHt + self.R
        K, L = kalman_gain(PHt, S)
        if self.joseph:
            IKH = jnp.eye(ts.dim, dtype=P.dtype) - K @ H
            P_new = IKH @ P @ IKH.T + K @ self.R @ K.T
        else:
            P_new = P - K @ S @ K.T
        return self._correct(ts, x, P, P_new, K, L, r, y_ok)
