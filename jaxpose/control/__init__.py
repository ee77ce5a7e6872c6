"""Control: time-varying LQR (Riccati in ``lax.scan``), iLQR with box control limits
(projected Newton), and differentiable MPC (implicit or unrolled gradients).

Status codes of solutions: ``CONVERGED`` (0), ``MAX_ITER`` (1), ``NONFINITE`` (2),
``STALLED`` (3); ``STATUS_NAMES`` maps each code to its description.
"""

from .boxqp import BoxQPResult, box_qp
from .cost import Cost, FunctionCost, QuadraticCost
from .ilqr import ILQRSolution, dynamics_jacobians, ilqr
from .lqr import (
    CONVERGED,
    LQR,
    MAX_ITER,
    NONFINITE,
    STALLED,
    STATUS_NAMES,
    LQRSolution,
    lq_problem,
    lqr,
    lqr_solve,
    riccati,
)
from .mpc import MPC, MPCSolution, closed_loop, implicit_vjp

__all__ = [
    "CONVERGED",
    "LQR",
    "MAX_ITER",
    "MPC",
    "NONFINITE",
    "STALLED",
    "STATUS_NAMES",
    "BoxQPResult",
    "Cost",
    "FunctionCost",
    "ILQRSolution",
    "LQRSolution",
    "MPCSolution",
    "QuadraticCost",
    "box_qp",
    "closed_loop",
    "dynamics_jacobians",
    "ilqr",
    "implicit_vjp",
    "lq_problem",
    "lqr",
    "lqr_solve",
    "riccati",
]
