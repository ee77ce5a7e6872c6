"""Sparse factor-graph least squares: stacked variables, grouped factors, block-sparse LM.

Marginal covariances of a solution: :func:`marginals` (:mod:`jaxpose.graph.marginals`).
The two ready-made problems are reached the same way: pose graphs by
:func:`optimize_pose_graph` / :func:`pose_graph_problem` (module :mod:`jaxpose.graph.pgo`;
global initialisation: :mod:`jaxpose.graph.init`) and bundle adjustment (BAL camera model,
Schur elimination of the points) by :func:`optimize_bal` / :func:`bundle_adjustment_problem`
(module :mod:`jaxpose.graph.ba`). Outlier-robust solves by graduated non-convexity:
:mod:`jaxpose.graph.robust`.
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
from .pgo import optimize_pose_graph, pose_graph_problem
from .problem import FactorGraph, GraphLinearization, cost, linearize
from .robust import GNCSolution, gm_weights, gnc, tls_weights, weighted_graph
from .solve import (
    PCG,
    Damping,
    GraphLinearSolver,
    GraphSolution,
    default_rtol,
    default_stopping,
    solve,
    summary,
)

__all__ = [
    "Damping",
    "Factor",
    "GNCSolution",
    "FactorGraph",
    "GraphLinearSolver",
    "GraphSolution",
    "GraphLinearization",
    "Marginals",
    "PCG",
    "ba",
    "between_jacobian",
    "between_residual",
    "bundle_adjustment_problem",
    "chordal_initialization",
    "cost",
    "default_rtol",
    "default_stopping",
    "init",
    "initial_poses",
    "gm_weights",
    "gnc",
    "linearize",
    "marginals",
    "optimize_bal",
    "optimize_pose_graph",
    "pgo",
    "pose_graph_cost",
    "pose_graph_problem",
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
