"""Inertial navigation: on-manifold IMU preintegration (Forster et al.) with covariance
and bias Jacobians, dead reckoning, IMU and GPS factors for the sparse least-squares
path, and a reader for GTSAM's IMU+GPS example stream. Conventions: ``docs/imu.md``.

``SCHEMES``: the preintegration schemes accepted by ``preintegrate(..., scheme=)``,
``"manifold"`` (Forster, associative scan) and ``"tangent"`` (GTSAM's first-order scheme).
Dead reckoning (the navigation state after every sample): :func:`dead_reckon`."""

from ._data import ImuGpsData, read_imu_gps
from ._factors import (
    ImuFactorData,
    bias_walk_factor,
    bias_walk_residual,
    gps_factor,
    gps_residual,
    imu_factor,
    imu_residual,
)
from ._fusion import FusionResult, fuse_imu_gps, preintegrate_windows
from ._preintegration import (
    SCHEMES,
    ImuPreintegrator,
    Preintegrated,
    dead_reckon,
    predict,
    preintegrate,
)
from ._state import NavState

__all__ = [
    "SCHEMES",
    "FusionResult",
    "ImuFactorData",
    "ImuGpsData",
    "ImuPreintegrator",
    "NavState",
    "Preintegrated",
    "bias_walk_factor",
    "bias_walk_residual",
    "fuse_imu_gps",
    "gps_factor",
    "gps_residual",
    "imu_factor",
    "imu_residual",
    "dead_reckon",
    "predict",
    "preintegrate",
    "preintegrate_windows",
    "read_imu_gps",
]
