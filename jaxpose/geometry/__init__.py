"""Geometry and vision: cameras, registration, nearest neighbours, ICP, PnP, splines,
trajectory metrics, rotation losses and point-cloud down-sampling.

All functions are pure and take/return arrays and :mod:`jaxpose.lie` groups (SE3 with
PyPose's ``[tx, ty, tz, qx, qy, qz, qw]`` storage); they jit, vmap and differentiate.
Shape and type errors raise at trace time naming the argument; conditions that depend
on values (degenerate configurations, non-finite data) come back as
:class:`jaxpose.Results` codes in the results.

Every name is exported here; the implementation modules are private.
"""

from ._camera import (
    bal_project,
    cart2homo,
    homo2cart,
    intrinsics_matrix,
    pixel2point,
    point2pixel,
    radial_distort,
    reprojerr,
)
from ._downsample import Downsampled, Filtered, knn_filter, nbr_filter, random_filter, voxel_filter
from ._icp import ICPResult, estimate_normals, icp
from ._kdtree import KDTree, build_kdtree, query_kdtree
from ._knn import KNNResult, knn
from ._losses import geodesic_angle, geodesic_loss
from ._metrics import ErrorStats, TrajectoryError, ape, associate, error_stats, rpe
from ._pnp import PnPResult, epnp
from ._registration import svdstf, svdtf, umeyama
from ._spline import bspline, bspline_se3, bspline_se3_fit, chspline, hermite

__all__ = [
    "Downsampled", "ErrorStats", "Filtered", "ICPResult", "KDTree", "KNNResult", "PnPResult",
    "TrajectoryError", "ape", "associate", "bal_project", "bspline", "bspline_se3",
    "bspline_se3_fit", "build_kdtree", "cart2homo", "chspline", "epnp", "error_stats",
    "estimate_normals", "geodesic_angle", "geodesic_loss", "hermite", "homo2cart", "icp",
    "intrinsics_matrix", "knn", "knn_filter", "nbr_filter", "pixel2point", "point2pixel",
    "query_kdtree", "radial_distort", "random_filter", "reprojerr", "rpe", "svdstf", "svdtf",
    "umeyama", "voxel_filter",
]
