"""Filters: EKF, UKF (Merwe scaled sigma points) and a bootstrap particle filter.

Step API (``predict``/``update``/``step``) and ``lax.scan`` runners (``run``) returning
per-step estimates and covariances; states may be arrays or Lie groups (error-state
updates through the retraction ``X ⊕ δ = X·Exp(δ)``).
"""

from ._common import FilterResult
from ._ekf import EKF
from ._pf import ParticleFilter, ParticleState, effective_sample_size, systematic_resample
from ._ukf import UKF, merwe_weights

__all__ = [
    "EKF",
    "UKF",
    "FilterResult",
    "ParticleFilter",
    "ParticleState",
    "effective_sample_size",
    "merwe_weights",
    "systematic_resample",
]
