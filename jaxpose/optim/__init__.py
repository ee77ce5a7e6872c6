"""Second-order least squares over pytrees of Lie groups and arrays.

``least_squares(residual_fn, params, args, solver=LevenbergMarquardt(...))`` minimises
``0.5 · Σ ρ(rᵀ W r)`` and returns a :class:`Solution`. Solvers also expose
``init``/``step`` for hand-driven iterations; :func:`covariance` gives the covariance of a
solution in its tangent chart (Ceres' ``Covariance``). See the module docstrings of
:mod:`~jaxpose.optim._problem` (conventions), :mod:`~jaxpose.optim._strategies`,
:mod:`~jaxpose.optim._kernels`, :mod:`~jaxpose.optim._correctors`,
:mod:`~jaxpose.optim._linear`, :mod:`~jaxpose.optim._stopping` and
:mod:`~jaxpose.optim._implicit`.
"""

from . import _kernels
from ._correctors import Corrector, FastTriggs, Triggs
from ._covariance import covariance
from ._implicit import ImplicitAdjoint, UnrolledAdjoint
from ._kernels import (
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
from ._linear import CG, LU, QR, SVD, Cholesky, LinearSolver
from ._problem import LinearizedResidual, Problem
from ._solution import Solution
from ._solve import least_squares
from ._solver import GN, LM, AbstractSolver, GaussNewton, LevenbergMarquardt, SolverState
from ._stopping import StopOnPlateau, Stopping
from ._strategies import (
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
    *_kernels.__all__,
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
