"""Sparse factor-graph least squares: stacked variables, grouped factors, block-sparse LM."""

from .factor import (
    Factor,
    between_jacobian,
    between_residual,
    prior_residual,
    vector_prior_residual,
)
from .problem import FactorGraph, Linearization, cost, linearize
from .solve import CONVERGED, MAX_STEPS, NON_FINITE, STALLED, GraphSolution, solve, summary

__all__ = [
    "CONVERGED",
    "MAX_STEPS",
    "NON_FINITE",
    "STALLED",
    "Factor",
    "FactorGraph",
    "GraphSolution",
    "Linearization",
    "between_residual",
    "cost",
    "linearize",
    "prior_residual",
    "solve",
    "summary",
    "vector_prior_residual",
]
