"""Sparse factor-graph least squares: stacked variables, grouped factors, block-sparse LM.

Marginal covariances of a solution: :func:`marginals`. The two ready-made problems are
reached the same way: pose graphs by :func:`optimize_pose_graph` / :func:`pose_graph_problem`
(global initialisation: :func:`chordal_initialization`, :func:`initial_poses` on the
host; :func:`chordal_poses`, :func:`initial_variables` in jit and vmap) and bundle
adjustment (BAL camera model, Schur elimination of the points) by :func:`optimize_bal` /
:func:`bundle_adjustment_problem`. Outlier-robust solves by graduated non-convexity:
:func:`gnc`; outlier tests of a solution: :func:`deletion_statistics`. Every name is
exported here; the implementation modules are private.
"""

from ._ba import (
    bal_to_variables,
    bundle_adjustment_problem,
    optimize_bal,
    reprojection_jacobian,
    reprojection_residual,
    reprojection_rmse,
    variables_to_bal,
)
from ._chordal import chordal_poses, initial_variables
from ._factor import (
    Factor,
    between_jacobian,
    between_residual,
    prior_residual,
    vector_prior_residual,
)
from ._init import chordal_initialization, initial_poses, pose_graph_cost
from ._marginals import Marginals, marginals, se3_to_gtsam
from ._pgo import optimize_pose_graph, pose_graph_problem
from ._problem import FactorGraph, GraphLinearization, cost, linearize
from ._robust import GNCSolution, chi2_quantile, gm_weights, gnc, tls_weights, weighted_graph
from ._snooping import deletion_statistics
from ._solve import (
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
    "bal_to_variables",
    "reprojection_rmse",
    "variables_to_bal",
    "Damping",
    "Factor",
    "GNCSolution",
    "FactorGraph",
    "GraphLinearSolver",
    "GraphSolution",
    "GraphLinearization",
    "Marginals",
    "PCG",
    "between_jacobian",
    "between_residual",
    "bundle_adjustment_problem",
    "chi2_quantile",
    "chordal_initialization",
    "chordal_poses",
    "cost",
    "default_rtol",
    "default_stopping",
    "deletion_statistics",
    "initial_poses",
    "initial_variables",
    "gm_weights",
    "gnc",
    "linearize",
    "marginals",
    "optimize_bal",
    "optimize_pose_graph",
    "pose_graph_cost",
    "pose_graph_problem",
    "prior_residual",
    "reprojection_jacobian",
    "reprojection_residual",
    "se3_to_gtsam",
    "solve",
    "summary",
    "tls_weights",
    "vector_prior_residual",
    "weighted_graph",
]
