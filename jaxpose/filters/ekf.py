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
    check_noise_dim,
    finite_tree,
    kalman_gain,
    noise_matrix,
    symmetrize,
)

Array = jax.Array


class EKF(eqx.Module):
    """``EKF(model, Q, R, joseph=True)``; ``Q`` (k, k) process noise in the state's
    tangent coordinates (k = n for vectors), ``R`` (p, p) measurement noise (PD)."""

    model: System
    Q: Array
    R: Array
    joseph: bool = eqx.field(static=True, default=True)

    def __init__(self, model: System, Q: Any, R: Any, joseph: bool = True):
        if not isinstance(model, System):
            raise TypeError(
                f"model: expected a jaxpose.dynamics.System, got {type(model).__name__}"
            )
        self.model = model
        self.Q = noise_matrix(Q, "Q")
        self.R = noise_matrix(R, "R", strict=True)
        self.joseph = joseph

    def predict(self, x: Any, P: Array, u: Array, t: Any = 0) -> tuple[Any, Array]:
        """``x⁻ = f(x, u, t)``, ``P⁻ = F P Fᵀ + Q``."""
        ts = tangent_space(x)
        check_noise_dim(self.Q, ts.dim, "Q", "state tangent size")
        xp, F = tangent_jacobian(lambda s: self.model.state_transition(s, u, t), x, ts, ts)
        return xp, symmetrize(F @ P @ F.T + self.Q)

    def update(self, x: Any, P: Array, y: Any, u: Array, t: Any = 0) -> tuple[Any, Array]:
        """Correct ``(x, P)`` with measurement ``y`` of ``h(x, u, t)``."""
        ts = tangent_space(x)
        yh = self.model.observation(x, u, t)
        ys = tangent_space(yh)
        check_noise_dim(self.R, ys.dim, "R", "measurement size")
        _, H = tangent_jacobian(lambda s: self.model.observation(s, u, t), x, ts, ys)
        r = ys.minus(y, yh)
        PHt = P @ H.T
        S = H @ PHt + self.R
        K, _ = kalman_gain(PHt, S)
        x_new = ts.plus(x, K @ r)
        if self.joseph:
            IKH = jnp.eye(ts.dim, dtype=P.dtype) - K @ H
            P_new = IKH @ P @ IKH.T + K @ self.R @ K.T
        else:
            P_new = P - K @ S @ K.T
        return x_new, symmetrize(P_new)

    def step(self, x: Any, P: Array, y: Any, u: Array, t: Any = 0) -> tuple[Any, Array]:
        """Predict with ``u`` then update with ``y``."""
        xp, Pp = self.predict(x, P, u, t)
        return self.update(xp, Pp, y, u, t)

    __call__ = step

    def run(self, x0: Any, P0: Any, ys: Any, us: Array, t0: Any = 0) -> FilterResult:
        """Filter a sequence with ``lax.scan``: ``ys`` (N, p), ``us`` (N, m); returns the
        N posterior estimates (after each update)."""
        P0 = check_cov(P0, tangent_space(x0).dim, "P0")
        return scan_filter(lambda x, P, y, u, t: self.step(x, P, y, u, t), x0, P0, ys, us, t0)


def scan_filter(step: Any, x0: Any, P0: Array, ys: Any, us: Array, t0: Any = 0) -> FilterResult:
    """Run ``step(x, P, y, u, t) → (x, P)`` over a sequence (shared by EKF and UKF)."""
    us = jnp.asarray(us)
    n_y = jax.tree.leaves(ys)[0].shape[0]
    if us.ndim != 2 or us.shape[0] != n_y:
        raise ValueError(
            f"us: expected shape ({n_y}, m) (one input per measurement), got {tuple(us.shape)}"
        )
    ts = jnp.asarray(t0) + jnp.arange(n_y)

    def body(carry: tuple[Any, Array], inp: tuple[Any, Array, Array]):
        x, P = carry
        y, u, t = inp
        x, P = step(x, P, y, u, t)
        return (x, P), (x, P, finite_tree(x, P))

    _, (xs, Ps, ok) = jax.lax.scan(body, (x0, P0), (ys, us, ts))
    return FilterResult(xs, Ps, ok)
