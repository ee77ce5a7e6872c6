"""Geometry and vision: cameras, registration, nearest neighbours, ICP, PnP, splines,
trajectory metrics, rotation losses and point-cloud down-sampling.

All functions are pure and take/return arrays and :mod:`jaxpose.lie` groups (SE3 with
PyPose's ``[tx, ty, tz, qx, qy, qz, qw]`` storage); they jit, vmap and differentiate.
Shape and type errors raise at trace time naming the argument; conditions that depend
on values (degenerate configurations, non-finite data) come back as
:class:`jaxpose.Results` codes in the results.

Modules: :mod:`.camera`, :mod:`.registration`, :mod:`.knn`, :mod:`.kdtree`, :mod:`.icp`,
:mod:`.pnp`, :mod:`.spline`, :mod:`.metrics`, :mod:`.losses`, :mod:`.downsample`. The
names ``icp`` and ``knn`` here are the functions (they shadow their modules; import
from those as ``from jaxpose.geometry.icp import ICPResult``).
"""

from . import camera, downsample, kdtree, losses, metrics, pnp, registration, spline
from .camera import (
    bal_project,
    cart2homo,
    homo2cart,
    intrinsics_matrix,
    pixel2point,
    point2pixel,
    radial_distort,
    reprojerr,
)
from .downsample import Downsampled, Filtered, knn_filter, nbr_filter, random_filter, voxel_filter
from .icp import ICPResult, estimate_normals, icp  # the function shadows the module
from .kdtree import KDTree, build_kdtree, query_kdtree
from .knn import KNNResult, knn  # the function shadows the module
from .losses import geodesic_angle, geodesic_loss
from .metrics import ErrorStats, TrajectoryError, ape, associate, error_stats, rpe
from .pnp import PnPResult, epnp
from .registration import svdstf, svdtf, umeyama
from .spline import bspline, bspline_se3, bspline_se3_fit, chspline, hermite

__all__ = [
    "Downsampled", "ErrorStats", "Filtered", "ICPResult", "KDTree", "KNNResult", "PnPResult",
    "TrajectoryError", "ape", "associate", "bal_project", "bspline", "bspline_se3",
    "bspline_se3_fit", "build_kdtree", "camera", "cart2homo", "chspline", "downsample",
    "epnp", "error_stats", "estimate_normals", "geodesic_angle", "geodesic_loss",
    "hermite", "homo2cart", "icp", "intrinsics_matrix", "kdtree", "knn", "knn_filter", "losses",
    "metrics", "nbr_filter", "pixel2point", "pnp", "point2pixel", "query_kdtree", "radial_distort",
    "random_filter", "registration", "reprojerr", "rpe", "spline", "svdstf", "svdtf",
    "umeyama", "voxel_filter",
]
