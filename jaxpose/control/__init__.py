"""Control: time-varying LQR (Riccati in ``lax.scan``), iLQR with box control limits
(projected Newton), and differentiable MPC (implicit or unrolled gradients).

Solutions carry an int32 ``status`` holding a :class:`jaxpose.Results` code.
"""

from ._boxqp import BoxQPResult, box_qp
from ._cost import Cost, FunctionCost, QuadraticCost
from ._ilqr import ILQRSolution, ilqr
from ._lqr import (
    LQR,
    LQRSolution,
    lq_problem,
    lqr,
    lqr_solve,
    riccati,
)
from ._mpc import MPC, MPCSolution, closed_loop

__all__ = [
    "LQR",
    "MPC",
    "BoxQPResult",
    "Cost",
    "FunctionCost",
    "ILQRSolution",
    "LQRSolution",
    "MPCSolution",
    "QuadraticCost",
    "box_qp",
    "closed_loop",
    "ilqr",
    "lq_problem",
    "lqr",
    "lqr_solve",
    "riccati",
]
