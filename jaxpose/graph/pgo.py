"""Pose-graph optimization: a :class:`~jaxpose.io.PoseGraph` in, optimised poses out.

Residual of an edge (i, j) with measurement Z: ``Log(Z⁻¹ · Xi⁻¹ · Xj)`` (translation
first), weighted by its information matrix Ω; cost ``0.5 · Σ ρ(rᵀΩr)``. The gauge is
fixed by holding the first pose (or the graph's FIX vertices) constant.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..lie import SE2, SE3
from .factor import Factor, between_jacobian, between_residual
from .problem import FactorGraph
from .solve import GraphSolution, solve

_GROUPS = {"SE3": SE3, "SE2": SE2}


def pose_graph_problem(
    graph: Any,
    *,
    kernel: Callable[[Any], Any] | None = None,
    fix: str = "first",
    dtype: Any = None,
) -> FactorGraph:
    """Build the factor graph of a :class:`~jaxpose.io.PoseGraph`.

    Args:
        graph: a ``PoseGraph`` (``kind``, ``poses``, ``edges``, ``measurements``,
            ``information``, ``fixed``).
        kernel: optional robust kernel ρ(s) applied to every edge.
        fix: ``"first"`` holds pose 0 constant; ``"file"`` holds the graph's FIX vertices
            (falling back to pose 0 when there are none); ``"none"`` fixes nothing (the
            problem is then gauge-free: use damping or a prior).
        dtype: float dtype of the variables (default: JAX's default float).
    """
    if graph.kind not in _GROUPS:
        raise ValueError(f"pose_graph_problem(graph): unsupported kind {graph.kind!r}")
    if fix not in ("first", "file", "none"):
        raise ValueError(f"pose_graph_problem(fix={fix!r}): expected 'first', 'file' or 'none'")
    group = _GROUPS[graph.kind]
    dtype = jnp.result_type(float) if dtype is None else dtype
    poses = group(jnp.asarray(graph.poses, dtype)).normalize()
    z = group(jnp.asarray(graph.measurements, dtype)).normalize()
    edges = np.asarray(graph.edges)
    factor = Factor(
        between_residual,
        [("pose", edges[:, 0]), ("pose", edges[:, 1])],
        data=z,
        information=np.asarray(graph.information),
        kernel=kernel,
        name=f"between_{graph.kind}",
        jacobian=between_jacobian,
    )
    fixed: dict[str, Any] = {}
    if fix == "first":
        fixed = {"pose": [0]}
    elif fix == "file":
        file_fixed = np.asarray(getattr(graph, "fixed", []), dtype=np.int64)
        fixed = {"pose": file_fixed if file_fixed.size else [0]}
    return FactorGraph([factor], {"pose": poses}, fixed=fixed)


def optimize_pose_graph(
    graph: Any, *, kernel: Any = None, fix: str = "first", dtype: Any = None, **solve_kwargs: Any
) -> tuple[np.ndarray, GraphSolution]:
    """Optimise a pose graph; returns (poses as numpy (n, storage), solution)."""
    problem = pose_graph_problem(graph, kernel=kernel, fix=fix, dtype=dtype)
    sol = solve(problem, **solve_kwargs)
    return np.asarray(sol.variables["pose"].data), sol
