"""Sparse factor-graph least squares: stacked variables, grouped factors, block-sparse LM.

Pose graphs: :mod:`jaxpose.graph.pgo`; outlier-robust solves by graduated non-convexity:
:mod:`jaxpose.graph.robust`; bundle adjustment (BAL camera model, Schur
elimination of the points): :mod:`jaxpose.graph.ba`.
"""

from . import ba, pgo, robust
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
from .problem import FactorGraph, Linearization, cost, linearize
from .robust import GNCSolution, gm_weights, gnc, tls_weights, weighted_graph
from .solve import CONVERGED, MAX_STEPS, NON_FINITE, STALLED, GraphSolution, solve, summary
from .strategies import LambdaFactor, Nielsen

__all__ = [
    "CONVERGED",
    "MAX_STEPS",
    "NON_FINITE",
    "STALLED",
    "Factor",
    "GNCSolution",
    "FactorGraph",
    "GraphSolution",
    "LambdaFactor",
    "Linearization",
    "Nielsen",
    "ba",
    "between_jacobian",
    "between_residual",
    "bundle_adjustment_problem",
    "cost",
    "gm_weights",
    "gnc",
    "linearize",
    "optimize_bal",
    "pgo",
    "prior_residual",
    "reprojection_jacobian",
    "reprojection_residual",
    "robust",
    "solve",
    "summary",
    "tls_weights",
    "vector_prior_residual",
    "weighted_graph",
]
