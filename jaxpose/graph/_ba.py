"""Bundle adjustment with the BAL camera model on the sparse factor-graph path.

Variables (types sorted by name, as every :class:`~jaxpose.graph.FactorGraph`):

* ``"intrinsics"`` (n_cam, 3): ``[f, k1, k2]`` per camera (plain vectors, additive steps);
* ``"point"`` (n_pt, 3): world points (eliminated by the Schur complement by default);
* ``"pose"`` SE3 (n_cam,): world → camera, ``P = pose · X``; right-perturbed.

BAL stores a camera as ``[r(3) Rodrigues, t(3), f, k1, k2]`` with ``P = Exp(r)·X + t``,
i.e. ``pose = (t, Exp(r))``. Camera model (:func:`jaxpose.geometry.bal_project`): ``p = −P[:2] /
P[2]``, ``pixel = f·(1 + k1‖p‖² + k2‖p‖⁴)·p``. One reprojection factor per observation,
residual ``pixel(pose, intrinsics, X) − z`` (pixels), cost ``0.5·Σ ρ(‖r‖²)`` (unit
information unless given).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..io._bal import BALProblem
from ..lie import SE3, SO3
from ..optim._strategies import Nielsen
from ._analysis import fixed_indices
from ._factor import Factor
from ._problem import FactorGraph
from ._reprojection import reprojection_jacobian, reprojection_residual
from ._solve import GraphLinearSolver, GraphSolution, solve

Array = jax.Array


def bal_to_variables(cameras: Any, points: Any, dtype: Any = None) -> dict[str, Any]:
    """BAL cameras (n, 9) and points (m, 3) → ``{"pose", "intrinsics", "point"}``."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    cam = jnp.asarray(cameras, dtype)
    if cam.ndim != 2 or cam.shape[1] != 9:
        raise ValueError(f"bal_to_variables(cameras): expected shape (n, 9), got {cam.shape}")
    pts = jnp.asarray(points, dtype)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"bal_to_variables(points): expected shape (m, 3), got {pts.shape}")
    return {"pose": _poses(cam[:, :3], cam[:, 3:6]), "intrinsics": cam[:, 6:9], "point": pts}


# one compiled program each (run op by op, the two conversions compiled ~30 tiny XLA
# programs: ~0.7 s of a cold `jaxpose ba`)
@jax.jit
def _poses(rotvec: Any, t: Any) -> SE3:
    return SE3.from_rotation_translation(SO3.exp(rotvec), t)


@jax.jit
def _rotvec_translation(pose: SE3) -> tuple[Any, Any]:
    return pose.rotation().log().data, pose.translation()


def variables_to_bal(variables: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`bal_to_variables`: (cameras (n, 9), points (m, 3)) in float64."""
    rot, t = _rotvec_translation(variables["pose"])
    cams = np.concatenate([np.asarray(rot, np.float64), np.asarray(t, np.float64),
                           np.asarray(variables["intrinsics"], np.float64)], axis=1)
    return cams, np.asarray(variables["point"], np.float64)


def bundle_adjustment_problem(
    problem: BALProblem,
    *,
    kernel: Callable[[Any], Any] | None = None,
    eliminate: bool = True,
    fix_intrinsics: bool = False,
    fixed_cameras: Any = (),
    dtype: Any = None,
) -> FactorGraph:
    """The factor graph of a :class:`~jaxpose.io.BALProblem`.

    Args:
        problem: cameras, points and observations (BAL conventions).
        kernel: optional robust kernel ρ(s) on every observation (s = ‖r‖² in pixels²).
        eliminate: build the Schur bookkeeping for ``"point"`` (``linear_solver="schur"``).
        fix_intrinsics: hold every camera's ``[f, k1, k2]`` constant.
        fixed_cameras: indices of cameras whose pose (and intrinsics) are held constant
            at their values in ``problem``. BA has a 7-dof gauge (similarity); by default
            nothing is fixed and LM's damping keeps the steps bounded, as in Ceres. Two
            held cameras remove the gauge (needed to differentiate the solution) but fix
            12 degrees of freedom, so their values must agree with the data: held at a
            rough initial guess they bias the whole solution.
        dtype: float dtype of the variables (default: JAX's default float).
    """
    if not isinstance(problem, BALProblem):
        raise TypeError(
            f"bundle_adjustment_problem(problem): expected a BALProblem, got "
            f"{type(problem).__name__}"
        )
    if problem.n_observations == 0:
        raise ValueError("bundle_adjustment_problem(problem): the problem has no observations")
    variables = bal_to_variables(problem.cameras, problem.points, dtype)
    obs = jnp.asarray(problem.observations, variables["point"].dtype)
    factor = Factor(
        reprojection_residual,
        [("pose", problem.camera_index), ("intrinsics", problem.camera_index),
         ("point", problem.point_index)],
        data=obs,
        kernel=kernel,
        name="reprojection_bal",
        jacobian=reprojection_jacobian,
    )
    cams = np.unique(fixed_indices(fixed_cameras, "bundle_adjustment_problem(fixed_cameras)"))
    fixed: dict[str, Any] = {}
    if cams.size:
        fixed = {"pose": cams, "intrinsics": cams}
    if fix_intrinsics:
        fixed["intrinsics"] = np.arange(problem.n_cameras)
    return FactorGraph([factor], variables, fixed=fixed,
                       eliminate="point" if eliminate else None)


def reprojection_rmse(problem: BALProblem, variables: dict[str, Any] | None = None) -> float:
    """Root-mean-square reprojection error per coordinate (pixels), numpy float64."""
    from ..io._bal import _bal_project_numpy

    if problem.observations.shape[0] == 0:
        raise ValueError("reprojection_rmse(problem): the problem has no observations, so "
                         "there is no error to average")

    cams, pts = (problem.cameras, problem.points) if variables is None else (
        variables_to_bal(variables))
    pred = _bal_project_numpy(cams, pts, problem.camera_index, problem.point_index)
    return float(np.sqrt(np.mean((pred - problem.observations) ** 2)))


def optimize_bal(
    problem: BALProblem,
    *,
    kernel: Any = None,
    linear_solver: str | GraphLinearSolver = "schur",
    fix_intrinsics: bool = False,
    fixed_cameras: Any = (),
    dtype: Any = None,
    **solve_kwargs: Any,
) -> tuple[BALProblem, GraphSolution]:
    """Bundle-adjust a BAL problem; returns (the optimised problem, the solution).
    ``linear_solver``: a method name or a :class:`~jaxpose.graph.GraphLinearSolver`
    (``"schur"`` eliminates the points).

    Defaults suited to BA (override through ``solve_kwargs``): Marquardt damping
    (``damping="diagonal"``) and Nielsen's rule from λ₀ = 1e-4
    (``strategy=Nielsen(1e-4)``), as Ceres' LM."""
    method = (linear_solver.method if isinstance(linear_solver, GraphLinearSolver)
              else linear_solver)
    graph = bundle_adjustment_problem(
        problem, kernel=kernel, eliminate=method == "schur",
        fix_intrinsics=fix_intrinsics, fixed_cameras=fixed_cameras, dtype=dtype,
    )
    opts: dict[str, Any] = dict(damping="diagonal", strategy=Nielsen(1e-4))
    opts.update(solve_kwargs)
    sol = solve(graph, linear_solver=linear_solver, **opts)
    cams, pts = variables_to_bal(sol.variables)
    out = BALProblem(cams, pts, problem.camera_index, problem.point_index,
                     problem.observations, problem.path)
    return out, sol
