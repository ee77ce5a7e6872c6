"""jaxpose: JAX-native Lie groups, least squares and differentiable robotics modules.

Public API: ``jaxpose.lie`` (groups, algebras, manifold calculus), re-exported here as
``jp.SO3``, ``jp.SE3``, ... (``jp.GROUPS`` and ``jp.ALGEBRAS``: tuples of the group and
algebra classes) and the functional ops ``jp.exp``, ``jp.log``, ...; the
subpackages ``optim`` (dense least squares), ``graph`` (sparse factor graphs, PGO, BA),
``io`` (g2o, BAL), ``dynamics``, ``filters``, ``control``, ``imu``, ``geometry``,
``sharding``, ``smoothing`` (fixed-lag smoother), ``interop`` and ``testing`` (a Lie-aware
``assert_close``); ``jp.compile_options()``: XLA options that shorten the compilation of
the solvers (for ``jax.jit(..., compiler_options=...)``).
"""

from . import (
    control,
    datasets,
    dynamics,
    filters,
    geometry,
    graph,
    imu,
    interop,
    io,
    lie,
    optim,
    results,
    sharding,
    smoothing,
    testing,
)
from ._compile import compile_options
from .datasets import synthetic_bal, synthetic_pose_graph
from .io import BALProblem, FormatError, PoseGraph, read_bal, read_g2o, write_bal, write_g2o
from .lie import *  # noqa: F403  (the groups and functional ops: lie.__all__)
from .results import Results

__version__ = "0.1.0"

__all__ = [
    "BALProblem", "FormatError", "PoseGraph", "Results", "__version__", "compile_options",
    "control", "datasets",
    "dynamics", "filters", "geometry", "graph", "imu", "interop", "io", "lie", "optim", "read_bal",
    "read_g2o", "sharding", "smoothing", "synthetic_bal", "synthetic_pose_graph", "testing",
    "write_bal", "write_g2o",
    *lie.__all__,
]
