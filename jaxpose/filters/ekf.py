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

from ..dynamics._tangent import tangent_jacobian, tangent_space
from ..dynamics.system import System
from ._common import (
    FilterResult,
    check_cov,
    check_measurement,
    check_noise_dim,
    check_sequence,
    finite_tree,
    innovation_ok,
    kalman_gain,
    model_and_noise,
    select_tree,
    symmetrize,
)

Array = jax.Array


class EKF(eqx.Module):
    """``EKF(model, Q, R, joseph=True, skip_nonfinite=False)``; ``Q`` (k, k) process noise
    in the state's tangent coordinates (k = n for vectors), ``R`` (p, p) measurement noise
    (PD). ``skip_nonfinite``: skip (predict only) a non-finite measurement or one whose
    normalised innovation overflows (see the module docstring)."""

    model: System
    Q: Array
    R: Array
    joseph: bool = eqx.field(static=True, default=True)
    skip_nonfinite: bool = eqx.field(static=True, default=False)

    def __init__(
        self, model: System, Q: Any, R: Any, joseph: bool = True, skip_nonfinite: bool = False
    ):
        self.model, self.Q, self.R = model_and_noise(model, Q, R)
        self.joseph = joseph
        self.skip_nonfinite = bool(skip_nonfinite)

    def predict(self, x: Any, P: Array, u: Array, t: Any = 0) -> tuple[Any, Array]:
        """``x⁻ = f(x, u, t)``, ``P⁻ = F P Fᵀ + Q``."""
        ts = tangent_space(x)
        check_noise_dim(P, ts.dim, "P", "state tangent size")
        check_noise_dim(self.Q, ts.dim, "Q", "state tangent size")
        xp, F = tangent_jacobian(lambda s: self.model.state_transition(s, u, t), x, ts, ts)
        return xp, symmetrize(F @ P @ F.T + self.Q)

    def update(self, x: Any, P: Array, y: Any, u: Array, t: Any = 0) -> tuple[Any, Array]:
        """Correct ``(x, P)`` with measurement ``y`` of ``h(x, u, t)``."""
        return self._update(x, P, y, u, t)[:2]

    def _update(self, x: Any, P: Array, y: Any, u: Array, t: Any) -> tuple[Any, Array, Array]:
        """:meth:`update` and whether the measurement was used."""
        ts = tangent_space(x)
        check_noise_dim(P, ts.dim, "P", "state tangent size")
        yh = self.model.observation(x, u, t)
        ys = tangent_space(yh)
        check_noise_dim(self.R, ys.dim, "R", f"measurement noise: h(x) gives {ys.dim} values")
        check_measurement(y, yh, self.R)
        _, H = tangent_jacobian(lambda s: self.model.observation(s, u, t), x, ts, ys)
        y, y_ok = _safe_measurement(y, yh, self.skip_nonfinite)
        r = ys.minus(y, yh)
        PHt = P @ H.T
        S = H @ PHt + self.R
        K, L = kalman_gain(PHt, S)
        use = y_ok & innovation_ok(L, r) if self.skip_nonfinite else y_ok
        r = jnp.where(use, r, 0.0)
        x_new = ts.plus(x, K @ r)
        if self.joseph:
            IKH = jnp.eye(ts.dim, dtype=P.dtype) - K @ H
            P_new = IKH @ P @ IKH.T + K @ self.R @ K.T
        else:
            P_new = P - K @ S @ K.T
        if self.skip_nonfinite:
            x_new, P_new = select_tree(use, (x_new, P_new), (x, P))
        return x_new, symmetrize(P_new), use

    def step(self, x: Any, P: Array, y: Any, u: Array, t: Any = 0) -> tuple[Any, Array]:
        """Predict with ``u`` then update with ``y``."""
        return self._step(x, P, y, u, t)[:2]

    def _step(self, x: Any, P: Array, y: Any, u: Array, t: Any) -> tuple[Any, Array, Array]:
        xp, Pp = self.predict(x, P, u, t)
        return self._update(xp, Pp, y, u, t)

    __call__ = step

    def run(self, x0: Any, P0: Any, ys: Any, us: Array, t0: Any = 0) -> FilterResult:
        """Filter a sequence with ``lax.scan``: ``ys`` (N, p), ``us`` (N, m); returns the
        N posterior estimates (after each update). Sizes are checked at trace time:
        ``P0`` against ``x0``, ``ys`` against ``h(x0)`` and ``R``, ``us`` against ``ys``."""
        P0 = check_cov(P0, tangent_space(x0).dim, "P0")
        us = check_sequence(self.model, self.R, x0, ys, us, t0)
        return scan_filter(self._step, x0, P0, ys, us, t0)


def _safe_measurement(y: Any, y_hat: Any, skip: bool) -> tuple[Any, Array]:
    """With ``skip``: ``(y, finite)`` where y is finite, else ``(y_hat, False)`` — the
    replaced value keeps NaN out of the (discarded) update and of its derivatives."""
    if not skip:
        return y, jnp.asarray(True)
    ok = finite_tree(y)
    return select_tree(ok, y, y_hat), ok


def scan_filter(step: Any, x0: Any, P0: Array, ys: Any, us: Array, t0: Any = 0) -> FilterResult:
    """Run ``step(x, P, y, u, t) → (x, P, used)`` over a sequence (shared by EKF and UKF)."""
    n_y = jax.tree.leaves(ys)[0].shape[0]
    ts = jnp.asarray(t0) + jnp.arange(n_y)

    def body(carry: tuple[Any, Array], inp: tuple[Any, Array, Array]):
        x, P = carry
        y, u, t = inp
        x, P, used = step(x, P, y, u, t)
        return (x, P), (x, P, used & finite_tree(x, P))

    _, (xs, Ps, ok) = jax.lax.scan(body, (x0, P0), (ys, us, ts))
    return FilterResult(xs, Ps, ok)
