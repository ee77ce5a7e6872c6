"""Online estimation over streams: a fixed-lag smoother that keeps the last K states,
marginalising the oldest into a Gaussian prior (``docs/smoothing.md``).

* :class:`FixedLagSmoother` — the smoother (jit-compiled updates of fixed shapes,
  vmappable over independent streams, marginal covariances of the window).
* :class:`PackedSmoother` — the same smoother held in one flat array between updates:
  the lowest per-update latency in an online loop (one array in and out of each call).
* :mod:`jaxpose.smoothing.examples` — ready-made streams: IMU + GPS
  (:func:`~jaxpose.smoothing.examples.imu_gps_smoother`) and the replay of a 2D pose graph
  (:func:`~jaxpose.smoothing.examples.pose_graph_replay`).
"""

from . import examples as examples
from ._fixed_lag import FixedLagSmoother as FixedLagSmoother
from ._packed import PackedSmoother as PackedSmoother

__all__ = ["FixedLagSmoother", "PackedSmoother", "examples"]
