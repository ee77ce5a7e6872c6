"""Sparse factor-graph least squares: stacked variables, grouped factors, block-sparse LM.

Marginal covariances of a solution: :func:`marginals` (:mod:`jaxpose.graph.marginals`).
Pose graphs: :mod:`jaxpose.graph.pgo` (global initialisation: :mod:`jaxpose.graph.init`);
outlier-robust solves by graduated non-convexity: :mod:`jaxpose.graph.robust`; bundle
adjustment (BAL camera model, Schur elimination of the points): :mod:`jaxpose.graph.ba`.
"""

from . import ba, init, pgo, robust
from .ba import (
    bundle_adjustment_problem,
    optimize_bal,
    reprojection_jacobian,
    reprojection_residual,
)
from .factor import (
    Factor,
    between_jacobian,
    between_residual,
    prior_residual,
    vector_prior_residual,
)
from .init import chordal_initialization, initial_poses, pose_graph_cost
from .marginals import Marginals, marginals, se3_to_gtsam
from .problem import FactorGraph, Linearization, cost, linearize
from .robust import GNCSolution, gm_weights, gnc, tls_weights, weighted_graph
from .solve import GraphSolution, solve, summary
from .strategies import LambdaFactor, Nielsen

__all__ = [
    "Factor",
    "GNCSolution",
    "FactorGraph",
    "GraphSolution",
    "LambdaFactor",
    "Linearization",
    "Marginals",
    "Nielsen",
    "ba",
    "between_jacobian",
    "between_residual",
    "bundle_adjustment_problem",
    "chordal_initialization",
    "cost",
    "init",
    "initial_poses",
    "gm_weights",
    "gnc",
    "linearize",
    "marginals",
    "optimize_bal",
    "pgo",
    "pose_graph_cost",
    "prior_residual",
    "reprojection_jacobian",
    "reprojection_residual",
    "se3_to_gtsam",
    "robust",
    "solve",
    "summary",
    "tls_weights",
    "vector_prior_residual",
    "weighted_graph",
]
