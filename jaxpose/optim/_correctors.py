"""Correctors: turn a robust kernel into an ordinary least-squares block.

For one residual block with whitened residual e (d,), Jacobian J (d, n), s = ‖e‖²
and the cost ``0.5 · ρ(s)``, the exact derivatives are

* gradient  g = ρ'(s) Jᵀ e,
* Hessian   H ≈ Jᵀ (ρ'(s) I + 2 ρ''(s) e eᵀ) J   (dropping the residual's own curvature).

A corrector returns (ẽ, J̃) such that the Gauss-Newton quantities of the corrected block,
J̃ᵀẽ and J̃ᵀJ̃, reproduce (an approximation of) g and H, so every linear solver and the
trust-region model work unchanged. The predicted decrease of a step δ is always
``−(gᵀδ + ½ δᵀ J̃ᵀJ̃ δ)`` with g = J̃ᵀẽ, so the gain ratio stays meaningful.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp

from .._safe import safe_sqrt
from ._kernels import Kernel, _check_param, _is_traced

Array = jax.Array


class Corrector(eqx.Module):
    """Base class. ``__call__(kernel, e (b, d), J (b, d, n)) -> (ẽ, J̃)`` per block b."""

    @abc.abstractmethod
    def __call__(self, kernel: Kernel, e: Array, jac: Array) -> tuple[Array, Array]:
        """Corrected block residuals and Jacobians.

        Args:
            kernel: the robust kernel ρ.
            e: whitened residual blocks (b, d).
            jac: whitened Jacobian blocks (b, d, n).

        Returns:
            ``(ẽ, J̃)`` of shapes (b, d) and (b, d, n).
        """


class FastTriggs(Corrector):
    """ẽ = √ρ'(s) e,  J̃ = √ρ'(s) J (PyPose's default corrector).

    J̃ᵀẽ = ρ' Jᵀe is the exact gradient; J̃ᵀJ̃ = ρ' JᵀJ drops the (usually negative)
    ρ'' term, so the model Hessian stays positive semi-definite: iteratively reweighted
    least squares."""

    def __call__(self, kernel: Kernel, e: Array, jac: Array) -> tuple[Array, Array]:
        s = jnp.sum(e * e, axis=-1)
        w = safe_sqrt(kernel.derivative(s))
        return w[:, None] * e, w[:, None, None] * jac


_MIN_D_OK = lambda v: (v > 0) & (v <= 1)  # noqa: E731  (Triggs' min_d, NaN fails)


class Triggs(Corrector):
    """Triggs et al. (1999, eq. 11) correction including the ρ'' curvature term:

    ẽ = √ρ' / (1 − α) · e,   J̃ = √ρ' (I − α e eᵀ / s) J,   α = 1 − √D,
    D = 1 + 2 s ρ''/ρ',

    where α is the root of ½α² − α − sρ''/ρ' = 0, so that J̃ᵀẽ = ρ' Jᵀe (exact gradient)
    and J̃ᵀJ̃ = Jᵀ(ρ' I + 2ρ'' e eᵀ)J (exact Gauss-Newton Hessian of ½ρ(‖e‖²)).

    When D < ``min_d`` the exact model Hessian is (nearly) indefinite along e (beyond the
    kernel's inflection point); D is then clamped to ``min_d`` so the model stays positive
    definite (curvature ρ'·min_d along e). ``negative_curvature=False`` reproduces Ceres,
    which applies the rank-one term only where ρ'' > 0 and otherwise falls back to
    :class:`FastTriggs`. Blocks with s = 0 or ρ' = 0 use the FastTriggs scaling.
    """

    min_d: float = 1e-2
    negative_curvature: bool = eqx.field(default=True, static=True)

    def __check_init__(self) -> None:
        # known values (Python, NumPy or concrete JAX) here, traced ones in __call__
        _check_param("Triggs", "min_d", self.min_d, _MIN_D_OK, "in (0, 1]")

    def __call__(self, kernel: Kernel, e: Array, jac: Array) -> tuple[Array, Array]:
        if _is_traced(self.min_d):  # 0 gave inf/NaN residuals, > 1 an overstated curvature
            e = eqx.error_if(e, ~jnp.all(_MIN_D_OK(self.min_d)),
                             "Triggs(min_d): min_d has to be in (0, 1]")
        s = jnp.sum(e * e, axis=-1)
        d1 = kernel.derivative(s)
        d2 = kernel.second_derivative(s)
        sqrt_d1 = safe_sqrt(d1)
        use = (s > 0) & (d1 > 0)
        if not self.negative_curvature:
            use = use & (d2 > 0)
        s_safe = jnp.where(use, s, 1.0)
        d1_safe = jnp.where(use, d1, 1.0)
        big_d = jnp.maximum(1.0 + 2.0 * s_safe * d2 / d1_safe, self.min_d)
        alpha = jnp.where(use, 1.0 - jnp.sqrt(big_d), 0.0)
        e_new = (sqrt_d1 / (1.0 - alpha))[:, None] * e
        ej = jnp.einsum("bd,bdn->bn", e, jac)  # eᵀJ per block
        proj = (alpha / s_safe)[:, None, None] * e[:, :, None] * ej[:, None, :]
        j_new = sqrt_d1[:, None, None] * (jac - proj)
        return e_new, j_new


__all__ = ["Corrector", "FastTriggs", "Triggs"]
