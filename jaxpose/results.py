"""One results vocabulary for every solver, filter, controller and geometry routine.

Every routine that can end in more than one way returns an int32 ``status`` array (one
entry per problem under ``vmap``) holding a :class:`Results` code. The codes mean the same
thing everywhere (least squares, factor graphs, GNC, LQR/iLQR/MPC, ICP, PnP, ...), so a
stored status array keeps its meaning. Each member carries a one-line ``message``;
:meth:`Results.name_of` and :meth:`Results.message_of` turn a status (Python int, scalar
or batched array) into text.
"""

from __future__ import annotations

import enum
from typing import Any

import numpy as np


class Results(enum.IntEnum):
    """Why a routine stopped; ``int(member)`` is the code stored in ``status`` arrays.

    ``Results.CONVERGED.message`` is the one-line explanation; comparisons with int32
    arrays work directly (``sol.status == Results.CONVERGED``)."""

    message: str

    def __new__(cls, value: int, message: str) -> Results:
        obj = int.__new__(cls, value)
        obj._value_ = value
        obj.message = message
        return obj

    RUNNING = (-1, "not finished (only seen when driving a solver's step by hand)")
    CONVERGED = (0, "converged: a tolerance was met, or a closed-form solution is well posed")
    MAX_STEPS = (1, "the iteration budget ran out before a tolerance was met")
    DIVERGED = (2, "stalled: no trial step lowers the cost at the damping (regularisation) "
                   "bound or after too many rejections, or Gauss-Newton's uphill steps "
                   "converged above the best point seen; the best estimate is kept")
    NON_FINITE = (3, "NaN/Inf appeared in the data, the cost or a step; the best finite "
                     "estimate is kept")
    DEGENERATE = (4, "the configuration does not determine the answer (e.g. collinear "
                     "points, too few correspondences)")

    @classmethod
    def name_of(cls, status: Any) -> str | np.ndarray:
        """Lower-case member name(s) of ``status``: a str for a Python int or 0-d array,
        else a numpy array of str of the same shape (e.g. ``"converged"``)."""
        return _lookup(cls, status, lambda m: m.name.lower())

    @classmethod
    def message_of(cls, status: Any) -> str | np.ndarray:
        """One-line message(s) of ``status`` (same shapes as :meth:`name_of`)."""
        return _lookup(cls, status, lambda m: m.message)


def _lookup(cls: type[Results], status: Any, field: Any) -> str | np.ndarray:
    try:
        codes = np.asarray(status)
    except Exception as err:  # a tracer: text needs concrete values
        raise TypeError(
            "status: expected a concrete int or int array (text cannot be produced inside "
            f"jit/vmap), got {type(status).__name__}") from err
    if codes.dtype.kind == "b":  # a mask like status == CONVERGED is not a status
        raise TypeError("status: expected integer status codes, got a bool array (a mask "
                        "such as status == Results.CONVERGED is not a status)")
    if codes.dtype.kind not in "iu" and not (
            codes.dtype.kind == "f" and np.all(np.isfinite(codes))
            and np.all(codes == np.round(codes))):
        raise TypeError(f"status: expected integer status codes, got dtype {codes.dtype}")
    known = {int(m): field(m) for m in cls}
    flat = [int(c) for c in codes.reshape(-1)]
    bad = sorted({c for c in flat if c not in known})
    if bad:
        raise ValueError(f"status: unknown result code(s) {bad}; expected one of "
                         f"{sorted(known)} ({', '.join(m.name for m in cls)})")
    if codes.ndim == 0:
        return known[flat[0]]
    return np.asarray([known[c] for c in flat], dtype=object).reshape(codes.shape).astype(str)


__all__ = ["Results"]
