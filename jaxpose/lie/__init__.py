"""Lie groups and algebras (PyPose storage layouts) and tangent-space calculus.

Groups: :class:`SO3`, :class:`SE3`, :class:`Sim3`, :class:`RxSO3`, :class:`SO2`,
:class:`SE2`; algebras: :class:`so3`, :class:`se3`, :class:`sim3`, :class:`rxso3`,
:class:`so2`, :class:`se2`; ``GROUPS`` and ``ALGEBRAS`` are tuples of these classes in
that order. See ``docs/conventions.md`` for layouts and Jacobian conventions.
"""

from . import convert, manifold, series
from ._base import InvalidValueError, LieAlgebra, LieGroup
from ._batchops import cumops, identity_like, random_like
from ._functional import (
    act,
    adj,
    adjT,
    compose,
    cumprod,
    euler,
    exp,
    from_euler,
    from_matrix,
    hat,
    identity,
    interpolate,
    inv,
    jinvp,
    jl,
    jl_inv,
    jr,
    jr_inv,
    log,
    matrix,
    normalize,
    random,
    rotation,
    scale,
    translation,
)
from ._rxso3 import RxSO3, rxso3
from ._se2 import SE2, se2
from ._se3 import SE3, se3
from ._sim3 import Sim3, sim3
from ._so2 import SO2, so2
from ._so3 import SO3, so3

GROUPS = (SO3, SE3, Sim3, RxSO3, SO2, SE2)
ALGEBRAS = (so3, se3, sim3, rxso3, so2, se2)

__all__ = [
    "ALGEBRAS", "GROUPS", "InvalidValueError", "LieAlgebra", "LieGroup", "RxSO3", "SE2", "SE3",
    "SO2", "SO3",
    "Sim3", "act", "adj", "adjT", "compose", "convert", "cumops", "cumprod", "euler", "exp",
    "from_euler", "from_matrix", "hat", "identity", "identity_like", "interpolate", "inv",
    "jinvp", "jl", "jl_inv", "jr", "jr_inv", "log", "manifold", "matrix", "normalize", "random",
    "random_like", "rotation", "rxso3", "scale", "se2", "se3", "series", "sim3", "so2", "so3",
    "translation",
]
