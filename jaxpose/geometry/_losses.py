"""Geodesic rotation loss (PyPose's ``geodesic_loss`` / ``GeodesicLoss``).

θ = ‖Log(R_x · R_y⁻¹)‖ ∈ [0, π] between the rotation parts of two group elements (SO3,
SE3, Sim3, RxSO3) or algebra elements (mapped through Exp first). It is computed from
quaternions (accurate near 0 and π) and its derivative at θ = 0 is 0, not NaN.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp

from .._safe import safe_norm
from ..lie import SO3, LieAlgebra, LieGroup
from ..lie._base import broadcast_batch
from ._util import Array

_REDUCTIONS = ("none", "mean", "sum")


def _rotation(x: Any, argname: str) -> SO3:
    if isinstance(x, LieAlgebra):
        x = x.exp()
    if not isinstance(x, LieGroup) or x.point_dim != 3:
        raise TypeError(f"geodesic_loss({argname}): expected a 3-D group or algebra element "
                        f"(SO3, SE3, Sim3, RxSO3 or their algebras), got {type(x).__name__}")
    r = x.rotation()
    return r if isinstance(r, SO3) else SO3(r.data)


def geodesic_angle(input: Any, target: Any) -> Array:
    """Per-element rotation angle ‖Log(R_input · R_target⁻¹)‖, batch shapes broadcast."""
    x, y = _rotation(input, "input"), _rotation(target, "target")
    broadcast_batch(x.shape, y.shape, what="geodesic_loss(input, target)")
    return safe_norm(x.compose(y.inv()).log().data)


def geodesic_loss(input: Any, target: Any, reduction: str = "mean") -> Array:
    """Geodesic distance between rotation parts; ``reduction`` ``'mean'`` (default),
    ``'sum'`` or ``'none'`` (the per-element angles, broadcast batch shape)."""
    if reduction not in _REDUCTIONS:
        raise ValueError(f"geodesic_loss(reduction): expected one of {_REDUCTIONS}, got "
                         f"{reduction!r}")
    theta = geodesic_angle(input, target)
    if reduction == "none":
        return theta
    return jnp.mean(theta) if reduction == "mean" else jnp.sum(theta)


__all__ = ["geodesic_angle", "geodesic_loss"]
