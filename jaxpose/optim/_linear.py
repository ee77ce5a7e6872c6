"""Dense linear solvers for the (damped) Gauss-Newton step, built on lineax.

Every solver answers ``solve(jac, res, hess, grad, diag_add) -> δ`` for the system

    (H + diag(a)) δ = −g,      H = J̃ᵀJ̃ (n, n), g = J̃ᵀẽ (n,), a = diag_add (n,) ≥ 0,

with J̃ (m, n) and ẽ (m,) the whitened, kernel-corrected Jacobian and residual. The
damping vector ``a`` is rebuilt from the undamped H for every trial, so damping never
compounds across rejected steps. Normal-equation solvers (Cholesky, LU, CG, SVD) use H
and g; :class:`QR` solves the equivalent augmented least-squares problem
``[J̃; diag(√a)] δ ≈ [−ẽ; 0]`` without squaring the condition number (it is not rank
revealing: undamped it needs J̃ of full column rank). No solver raises on a singular or
indefinite system: the step comes back non-finite or meaningless (SVD instead returns the
minimum-norm pseudo-inverse step) and the optimiser treats a non-finite one as a failed
trial. Any positive damping (LM) makes every solver well posed.

On the coloured Jacobian path (``jacobian="sparse"``/``"auto"``) H may be structured; the
solver class chosen by the user stays the same and runs on that form:

* :class:`~jaxpose.optim._colouring.BlockHessian` (independent column groups): Cholesky, LU
  and SVD factorise its small diagonal blocks one by one (batched); CG and QR use the
  dense matrices.
* :class:`~jaxpose.optim._sparse_hessian.SparseHessian` (large sparse H in CSR, e.g.
  banded): :class:`Cholesky` is a sparse Cholesky (CHOLMOD on the host, symbolic analysis
  cached; :func:`jaxpose.graph._linear.solve_sparse_direct`), :class:`CG` runs matrix-free
  on the CSR product. :class:`LU` and :class:`SVD` densify H and :class:`QR` the Jacobian
  (dense fallback: pivoting and rank revelation are what they are chosen for, and they
  have no sparse counterpart here), so they cost what they cost on the dense path.
"""

from __future__ import annotations

import abc
import numbers

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx

from .._checks import count_field
from .._safe import safe_sqrt
from ._colouring import BlockHessian, as_dense
from ._sparse_hessian import SparseHessian
from ._stopping import check_tolerance

Array = jax.Array


class LinearSolver(eqx.Module):
    """Base class for the step's linear solve."""

    @abc.abstractmethod
    def solve(self, jac: Array, res: Array, hess: Array, grad: Array, diag_add: Array) -> Array:
        """Solve (H + diag(a)) δ = −g for the step δ (n,).

        Args:
            jac: whitened, corrected Jacobian J̃ (m, n) (used by :class:`QR`).
            res: whitened, corrected residual ẽ (m,) (used by :class:`QR`).
            hess: H = J̃ᵀJ̃ (n, n).
            grad: g = J̃ᵀẽ (n,).
            diag_add: damping a ≥ 0 added to the diagonal (n,).

        Returns:
            δ (n,); non-finite when the system is singular (the optimiser rejects the trial).
        """

    def _normal(self, hess: Array, diag_add: Array, tags: object = ()) -> lx.MatrixLinearOperator:
        a = hess + jnp.diag(diag_add)
        return lx.MatrixLinearOperator(a, tags)


class Cholesky(LinearSolver):
    """Cholesky of the damped normal matrix (default; H + diag(a) must be SPD): dense,
    batched over the blocks of a ``BlockHessian``, sparse (CHOLMOD) on a ``SparseHessian``."""

    def solve(self, jac: Array, res: Array, hess: Array, grad: Array, diag_add: Array) -> Array:
        if isinstance(hess, BlockHessian):
            return hess.solve(-grad, diag_add, "cholesky")
        if isinstance(hess, SparseHessian):
            return hess.solve(-grad, diag_add)
        op = self._normal(hess, diag_add, lx.positive_semidefinite_tag)
        return lx.linear_solve(op, -grad, lx.Cholesky(), throw=False).value


class LU(LinearSolver):
    """LU with partial pivoting of the damped normal matrix."""

    def solve(self, jac: Array, res: Array, hess: Array, grad: Array, diag_add: Array) -> Array:
        if isinstance(hess, BlockHessian):
            return hess.solve(-grad, diag_add, "lu")
        op = self._normal(as_dense(hess), diag_add)
        return lx.linear_solve(op, -grad, lx.LU(), throw=False).value


class QR(LinearSolver):
    """Householder QR of the augmented Jacobian [J̃; diag(√a)] (m + n, n)."""

    def solve(self, jac: Array, res: Array, hess: Array, grad: Array, diag_add: Array) -> Array:
        jac = as_dense(jac)
        # √a with a zero derivative at a = 0 (Gauss–Newton, Dogleg: no damping), where the
        # plain root's infinite one made a NaN through the unrolled adjoint
        aug = jnp.concatenate([jac, jnp.diag(safe_sqrt(diag_add))], 0)
        rhs = jnp.concatenate([-res, jnp.zeros_like(diag_add)])
        return lx.linear_solve(lx.MatrixLinearOperator(aug), rhs, lx.QR(), throw=False).value


class SVD(LinearSolver):
    """Pseudo-inverse via SVD of the damped normal matrix: the minimum-norm step for
    rank-deficient systems (singular values below ``rcond·σ_max`` are dropped)."""

    rcond: float | None = eqx.field(default=None, static=True)

    def __check_init__(self) -> None:
        check_rcond(self.rcond, "SVD(rcond)")

    def solve(self, jac: Array, res: Array, hess: Array, grad: Array, diag_add: Array) -> Array:
        if isinstance(hess, BlockHessian):
            return hess.solve(-grad, diag_add, "svd", self.rcond)
        op = self._normal(as_dense(hess), diag_add)
        return lx.linear_solve(op, -grad, lx.SVD(rcond=self.rcond), throw=False).value


class CG(LinearSolver):
    """Conjugate gradients on the damped normal matrix (matrix-free in lineax; on a
    ``SparseHessian`` through its CSR product).

    ``rtol``/``atol`` are CG's residual tolerances (static: a solver passed through
    ``jax.jit`` keeps them as Python floats); ``max_steps`` defaults to 10·n."""

    rtol: float = eqx.field(default=1e-10, static=True)
    atol: float = eqx.field(default=1e-12, static=True)
    max_steps: int | None = count_field("CG(max_steps)", optional=True, default=None)

    def __check_init__(self) -> None:
        # a NaN tolerance or no step gives δ = 0, which the stopping rules would read
        # as convergence
        check_tolerance(self.rtol, "CG(rtol)")
        check_tolerance(self.atol, "CG(atol)")

    def solve(self, jac: Array, res: Array, hess: Array, grad: Array, diag_add: Array) -> Array:
        n = grad.shape[0]
        steps = 10 * max(n, 1) if self.max_steps is None else self.max_steps
        psd = lx.positive_semidefinite_tag
        if isinstance(hess, SparseHessian):  # matrix-free on the CSR product
            op = lx.FunctionLinearOperator(lambda v: hess @ v + diag_add * v,
                                           jax.ShapeDtypeStruct(grad.shape, grad.dtype), psd)
        else:
            op = self._normal(as_dense(hess), diag_add, psd)
        tol_floor = 10 * jnp.finfo(grad.dtype).eps
        solver = lx.CG(rtol=max(self.rtol, float(tol_floor)), atol=self.atol, max_steps=steps)
        return lx.linear_solve(op, -grad, solver, throw=False).value


def check_rcond(rcond: object, name: str) -> None:
    """Refuse a cut-off ratio outside [0, 1) or NaN: at 1 or above every singular value is
    dropped (a zero step or covariance), NaN drops them all too."""
    if rcond is None or (not isinstance(rcond, bool) and isinstance(rcond, numbers.Real)
                         and 0 <= rcond < 1):
        return
    raise ValueError(f"{name}={rcond!r}: expected None or a float in [0, 1) (singular values "
                     f"below rcond·σ_max are dropped)")


__all__ = ["LinearSolver", "Cholesky", "LU", "QR", "SVD", "CG"]
