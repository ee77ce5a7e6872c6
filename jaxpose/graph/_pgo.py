"""Pose-graph optimization: a :class:`~jaxpose.io.PoseGraph` in, optimised poses out.

Residual of an edge (i, j) with measurement Z: ``Log(Z⁻¹ · Xi⁻¹ · Xj)`` (translation
first), weighted by its information matrix Ω; cost ``0.5 · Σ ρ(rᵀΩr)``. The gauge is
fixed by holding the first pose (or the graph's FIX vertices) constant.

Disconnected graphs (documented behaviour): every connected piece has its own gauge
freedom, so with ``fix="first"`` (or ``"file"``) the first pose of each piece that has
no fixed pose is held constant as well; the pieces are then solved jointly but
independently (their cost is the sum of the pieces' costs). ``fix="none"`` leaves every
gauge free (LM's damping keeps the steps finite).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..io._g2o import _apply_policy
from ..lie import SE2, SE3
from ._chordal import DENSE_MAX, initial_variables
from ._factor import Factor, between_residual
from ._init import gauge_anchors, initial_poses
from ._problem import FactorGraph
from ._solve import solve

_GROUPS = {"SE3": SE3, "SE2": SE2}


@functools.partial(jax.jit, static_argnums=0)
def _normalized(group: type, data: jax.Array) -> Any:
    """``group(data).normalize()`` as one compiled program (run op by op, it compiled
    ~20 tiny XLA programs: ~0.6 s of a cold ``jaxpose pgo``)."""
    return group(data).normalize()


def pose_graph_problem(
    graph: Any,
    *,
    kernel: Callable[[Any], Any] | None = None,
    fix: str = "first",
    dtype: Any = None,
    information: str | None = None,
    poses: Any = None,
) -> FactorGraph:
    """Build the factor graph of a :class:`~jaxpose.io.PoseGraph`.

    Args:
        graph: a ``PoseGraph`` (``kind``, ``poses``, ``edges``, ``measurements``,
            ``information``, ``fixed``).
        kernel: optional robust kernel ρ(s) applied to every edge.
        fix: ``"first"`` holds pose 0 constant; ``"file"`` holds the graph's FIX vertices
            (falling back to pose 0 when there are none); ``"none"`` fixes nothing (the
            problem is then gauge-free: use damping or a prior). With ``"first"`` and
            ``"file"``, each further disconnected piece without a fixed pose has its first
            pose held constant too (module docstring).
        dtype: float dtype of the variables (default: JAX's default float).
        information: ``None`` uses ``graph.information`` as it is; ``"strict"``,
            ``"repair"`` or ``"isotropic"`` applies that policy first
            (:func:`jaxpose.io.apply_information_policy`).
        poses: optional (n, 7)/(n, 4) starting poses instead of ``graph.poses`` (e.g. from
            :func:`jaxpose.graph.initial_poses`).
    """
    if graph.kind not in _GROUPS:
        raise ValueError(f"pose_graph_problem(graph): unsupported kind {graph.kind!r}")
    if fix not in ("first", "file", "none"):
        raise ValueError(f"pose_graph_problem(fix={fix!r}): expected 'first', 'file' or 'none'")
    group = _GROUPS[graph.kind]
    dtype = jnp.result_type(float) if dtype is None else dtype
    start = graph.poses if poses is None else getattr(poses, "data", poses)
    if np.shape(start) != np.shape(graph.poses):
        raise ValueError(
            f"pose_graph_problem(poses): expected shape {np.shape(graph.poses)} "
            f"like graph.poses, got {np.shape(start)}"
        )
    poses = _normalized(group, jnp.asarray(start, dtype))
    z = _normalized(group, jnp.asarray(graph.measurements, dtype))
    edges = np.asarray(graph.edges)
    factor = Factor(
        between_residual,
        [("pose", edges[:, 0]), ("pose", edges[:, 1])],
        data=z,
        information=(
            np.asarray(graph.information)
            if information is None
            else _apply_policy(graph.information, information, "pose_graph_problem")[0]
        ),
        kernel=kernel,
        name=f"between_{graph.kind}",
    )
    fixed: dict[str, Any] = {}
    if fix != "none":
        file_fixed = np.asarray(getattr(graph, "fixed", []), dtype=np.int64)
        held = file_fixed if (fix == "file" and file_fixed.size) else np.zeros(1, np.int64)
        fixed = {"pose": gauge_anchors(graph, held)}
    return FactorGraph([factor], {"pose": poses}, fixed=fixed)


def start_in_solve(graph: Any, init: str, fix: str = "first") -> bool:
    """Whether :func:`optimize_pose_graph` and ``jaxpose pgo`` compute the starting poses
    inside the compiled solve (:func:`solve_from_start`): ``init`` ``"auto"`` or
    ``"chordal"``, a held pose per piece (``fix`` ``"first"`` or ``"file"``) and at most
    600 tangent dimensions (the graphs ``solve`` solves densely); otherwise on the host
    (:func:`~jaxpose.graph.initial_poses`, sparse). Same poses either way."""
    dim = _GROUPS[graph.kind].tangent_dim if graph.kind in _GROUPS else 0
    return (init in ("auto", "chordal") and fix in ("first", "file") and graph.n_edges > 0
            and 0 < graph.n_poses * dim <= DENSE_MAX)


@eqx.filter_jit
def solve_from_start(problem: FactorGraph, init: str, **solve_kwargs: Any) -> tuple[Any, Any]:
    """``(solution, chordal)``: :func:`~jaxpose.graph.solve` of a pose-graph ``problem``
    from :func:`~jaxpose.graph.initial_variables` ``(problem, init)`` in one program
    (``chordal``: a bool array, whether the chordal poses were used)."""
    start, chordal = initial_variables(problem, init)
    return solve(problem, start, **solve_kwargs), chordal


def odometry_edges(graph: Any) -> np.ndarray:
    """(m,) booleans: edges joining consecutive poses (``|i − j| = 1``), the odometry
    (known inliers for :func:`~jaxpose.graph.gnc`); the others are loop closures."""
    edges = np.asarray(graph.edges)
    return np.abs(edges[:, 1] - edges[:, 0]) == 1


def optimize_pose_graph(
    graph: Any,
    *,
    kernel: Any = None,
    fix: str = "first",
    dtype: Any = None,
    init: str = "auto",
    information: str | None = None,
    robust: str | None = None,
    gnc_options: dict[str, Any] | None = None,
    **solve_kwargs: Any,
) -> tuple[np.ndarray, Any]:
    """Optimise a pose graph; returns (poses as numpy (n, storage), solution).

    ``init``: ``"auto"`` (default), ``"chordal"`` or ``"odometry"``, the starting poses of
    :func:`jaxpose.graph.initial_poses` (computed in the compiled solve for graphs of at
    most 600 tangent dimensions: :func:`start_in_solve`; with ``robust="gnc"``,
    ``"auto"`` starts from the file's/odometry poses: outliers corrupt the chordal
    relaxation); ``information``:
    as in :func:`pose_graph_problem`; other keywords go to :func:`jaxpose.graph.solve`.

    ``robust="gnc"``: graduated non-convexity (:func:`~jaxpose.graph.gnc`, TLS by default)
    with the odometry edges as known inliers; ``gnc_options`` are its keywords
    (``surrogate``, ``barc_sq``, ...), ``solve_kwargs`` those of the inner solve; the
    solution is a :class:`~jaxpose.graph.GNCSolution` (``weights[0]``: per-edge inlier
    weights). ``robust=None``: one LM solve (:func:`~jaxpose.graph.solve`)."""
    if robust not in (None, "gnc"):
        raise ValueError(f"optimize_pose_graph(robust={robust!r}): expected None or 'gnc'")
    if robust == "gnc" and kernel is not None:
        raise ValueError("optimize_pose_graph(kernel, robust='gnc'): give one, not both")
    if robust is None and gnc_options:
        raise ValueError("optimize_pose_graph(gnc_options): used by robust='gnc' only; add "
                         "robust='gnc' or drop gnc_options")
    if information is not None:
        info, _ = _apply_policy(graph.information, information, "optimize_pose_graph")
        graph = replace(graph, information=info)
    if robust == "gnc" and init == "auto":
        init = "odometry"
    if robust is None and start_in_solve(graph, init, fix):
        problem = pose_graph_problem(graph, kernel=kernel, fix=fix, dtype=dtype)
        sol = solve_from_start(problem, init, **solve_kwargs)[0]
        return np.asarray(sol.variables["pose"].data), sol
    start, _ = initial_poses(graph, init, fix=fix)  # after the policy: chordal uses Ω
    problem = pose_graph_problem(graph, kernel=kernel, fix=fix, dtype=dtype, poses=start)
    if robust == "gnc":
        from ._robust import gnc

        options = dict(gnc_options or {})
        options.setdefault("known_inliers", odometry_edges(graph))
        sol = gnc(problem, **options, **solve_kwargs)
    else:
        sol = solve(problem, **solve_kwargs)
    return np.asarray(sol.variables["pose"].data), sol
