"""Second-order least squares over pytrees of Lie groups and arrays.

``least_squares(residual_fn, params, args, solver=LevenbergMarquardt(...))`` minimises
``0.5 · Σ ρ(rᵀ W r)`` and returns a :class:`Solution`. Solvers also expose
``init``/``step`` for hand-driven iterations; :func:`covariance` gives the covariance of a
solution in its tangent chart (Ceres' ``Covariance``). See the module docstrings of
:mod:`~jaxpose.optim.problem` (conventions), :mod:`~jaxpose.optim.strategies`,
:mod:`~jaxpose.optim.kernels`, :mod:`~jaxpose.optim.correctors`,
:mod:`~jaxpose.optim.linear`, :mod:`~jaxpose.optim.stopping` and
:mod:`~jaxpose.optim.implicit`.
"""

from . import kernels
from .correctors import Corrector, FastTriggs, Triggs
from .covariance import covariance
from .implicit import ImplicitAdjoint, UnrolledAdjoint
from .kernels import (
    Arctan,
    Cauchy,
    GemanMcClure,
    Huber,
    Kernel,
    PseudoHuber,
    Scale,
    SoftLOne,
    Tolerant,
    Trivial,
    Tukey,
    Welsch,
)
from .linear import CG, LU, QR, SVD, Cholesky, LinearSolver
from .problem import LinearizedResidual, Problem
from .solution import Solution
from .solve import least_squares
from .solver import GN, LM, AbstractSolver, GaussNewton, LevenbergMarquardt, SolverState
from .stopping import StopOnPlateau, Stopping
from .strategies import (
    Adaptive,
    Constant,
    Dogleg,
    LambdaFactor,
    Nielsen,
    NielsenState,
    NormalEquations,
    Strategy,
    TrustRegion,
)

__all__ = [
    "least_squares",
    "covariance",
    "Solution",
    "Problem",
    "LinearizedResidual",
    "AbstractSolver",
    "GaussNewton",
    "LevenbergMarquardt",
    "GN",
    "LM",
    "SolverState",
    "Strategy",
    "NormalEquations",
    "Constant",
    "Adaptive",
    "TrustRegion",
    "Dogleg",
    "LambdaFactor",
    "Nielsen",
    "NielsenState",
    *kernels.__all__,
    "Corrector",
    "FastTriggs",
    "Triggs",
    "LinearSolver",
    "Cholesky",
    "QR",
    "LU",
    "CG",
    "SVD",
    "Stopping",
    "StopOnPlateau",
    "ImplicitAdjoint",
    "UnrolledAdjoint",
]
