"""Bundle Adjustment in the Large (BAL) problems: :class:`BALProblem`, :func:`read_bal`,
:func:`write_bal`. The BAL camera model is :func:`jaxpose.geometry.bal_project`; this module
keeps a private numpy float64 twin of it (``_bal_project_numpy``) for the seeded data generators
and file checks, which must not depend on ``jax_enable_x64``.

File layout (whitespace-separated tokens; line breaks are not significant)::

    n_cameras n_points n_observations
    camera point u v                     (n_observations times)
    9 parameters per camera              (Rodrigues r(3), t(3), f, k1, k2)
    3 coordinates per point

Camera model: ``P = R(r)·X + t``, ``p = −P[:2] / P[2]``, ``ρ = 1 + k1‖p‖² + k2‖p‖⁴``,
``pixel = f·ρ·p``; points in front of a camera have ``P[2] < 0``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from .._checks import set_numpy_field
from ..lie._numpy import rodrigues_rotate
from ._errors import FormatError
from ._text import describe_bad_char, first_bad_char, read_text, refuse_nonfinite_rows

__all__ = ["BALProblem", "read_bal", "write_bal"]

PathLike = str | os.PathLike[str]


@dataclass(frozen=True, eq=False, repr=False)
class BALProblem:
    """A bundle-adjustment problem; plain float64/int64 numpy arrays.

    Attributes:
        cameras: (n_cam, 9) Rodrigues rotation (3), translation (3), f, k1, k2.
        points: (n_pt, 3) world points.
        camera_index: (n_obs,) int64 camera of each observation.
        point_index: (n_obs,) int64 point of each observation.
        observations: (n_obs, 2) pixel coordinates (BAL: origin at the image centre).
        path: the file it was read from, if any.
    """

    cameras: np.ndarray
    points: np.ndarray
    camera_index: np.ndarray
    point_index: np.ndarray
    observations: np.ndarray
    path: str | None = None

    def __post_init__(self) -> None:
        set_ = lambda name, value: object.__setattr__(self, name, value)
        check = partial(set_numpy_field, self)
        check("cameras", np.float64, (None, 9))
        check("points", np.float64, (None, 3))
        check("camera_index", np.int64, (None,))
        n_obs = self.camera_index.shape[0]
        check("point_index", np.int64, (n_obs,))
        check("observations", np.float64, (n_obs, 2))
        if self.path is not None:
            set_("path", os.fspath(self.path))
        for name, n in (("camera_index", self.n_cameras), ("point_index", self.n_points)):
            idx = getattr(self, name)
            if idx.size and (idx.min() < 0 or idx.max() >= n):
                raise ValueError(f"BALProblem.{name}: indices must lie in [0, {n})")

    @property
    def n_cameras(self) -> int:
        """Number of cameras."""
        return int(self.cameras.shape[0])

    @property
    def n_points(self) -> int:
        """Number of 3-D points."""
        return int(self.points.shape[0])

    @property
    def n_observations(self) -> int:
        """Number of 2-D observations."""
        return int(self.observations.shape[0])

    def __repr__(self) -> str:
        return (
            f"BALProblem(n_cameras={self.n_cameras}, n_points={self.n_points}, "
            f"n_observations={self.n_observations}, path={self.path!r})"
        )


def _bal_project_numpy(
    cameras: np.ndarray,
    points: np.ndarray,
    camera_index: np.ndarray | None = None,
    point_index: np.ndarray | None = None,
) -> np.ndarray:
    """BAL projection in numpy float64: the host twin of :func:`jaxpose.geometry.bal_project`
    (same model, argument order ``cameras, points``), independent of ``jax_enable_x64``.

    Args:
        cameras: (n_cam, 9) or (..., 9) camera parameters.
        points: (n_pt, 3) or (..., 3) points.
        camera_index, point_index: (n_obs,) indices pairing cameras with points; when omitted,
            ``cameras`` and ``points`` are paired elementwise (broadcasting).

    Returns:
        (n_obs, 2) (or broadcast (..., 2)) predicted pixels.
    """
    cam = np.asarray(cameras, np.float64)
    X = np.asarray(points, np.float64)
    if camera_index is not None:
        cam = cam[np.asarray(camera_index)]
    if point_index is not None:
        X = X[np.asarray(point_index)]
    P = rodrigues_rotate(cam[..., :3], X) + cam[..., 3:6]
    p = -P[..., :2] / P[..., 2:3]
    n2 = np.sum(p * p, -1, keepdims=True)
    radial = 1.0 + cam[..., 7:8] * n2 + cam[..., 8:9] * n2 * n2
    return cam[..., 6:7] * radial * p


# ----------------------------------------------------------------------------- reading


def _line_of(lines: list[str], k: int) -> int:
    """1-based line holding token ``k`` (0-based) of the file; the last line if past the end."""
    seen = 0
    last = 1
    for ln, line in enumerate(lines, 1):
        n = len(line.split())
        if n:
            last = ln
        seen += n
        if seen > k:
            return ln
    return last


def _convert(
    path: PathLike,
    lines: list[str],
    tokens: list[str],
    start: int,
    dtype: Any,
    record: str,
    names: tuple[str, ...],
) -> np.ndarray:
    """1-D array from ``tokens`` (file tokens from ``start`` on), records of ``len(names)``
    fields; a bad token raises FormatError naming its line, record and field."""
    try:
        return np.array(tokens, dtype=dtype)
    except (ValueError, OverflowError):
        pass
    what = "an integer" if dtype is np.int64 else "a number"
    for k, tok in enumerate(tokens):
        try:
            np.array([tok], dtype=dtype)
        except (ValueError, OverflowError):
            r, c = divmod(k, len(names))
            where = record if record == "header" else f"{record} {r}"
            line = _line_of(lines, start + k)
            raise FormatError(
                path, line, f"{where}: expected {what} for {names[c]}, found {tok!r}"
            ) from None
    raise AssertionError("unreachable: conversion failed but no bad token found")


def read_bal(path: PathLike) -> BALProblem:
    """Read a BAL problem file.

    Returns:
        A :class:`BALProblem` with float64 parameters and int64 indices.

    The text is UTF-8 (a leading byte-order mark is dropped) and must be ASCII: ``1_0``,
    non-ASCII digits and non-ASCII spaces are rejected although Python's ``int``/``float``
    accept them. A point at a camera centre (depth 0) is read as it is; its projection is
    not finite (``jaxpose ba`` reports it before solving).

    Raises:
        FormatError: ``"FILE:LINE: ..."`` for a bad header, non-integer or out-of-range
            indices, non-numeric or non-finite values, non-ASCII or ``_`` characters, invalid
            UTF-8, too few values for the counts in the header, or values left over after
            them; the line is that of the offending token.
        OSError: the file cannot be read.
    """
    text = read_text(path)
    lines = text.split("\n")
    bad = first_bad_char(text)
    if bad >= 0:
        line = text.count("\n", 0, bad) + 1
        start = text.rfind("\n", 0, bad) + 1
        _, found = describe_bad_char(lines[line - 1], bad - start)
        raise FormatError(path, line, f"expected ASCII numbers separated by spaces, {found}")
    tokens = text.split()
    if len(tokens) < 3:
        raise FormatError(
            path,
            _line_of(lines, len(tokens)),
            f"expected a header 'n_cameras n_points n_observations', found {len(tokens)} values",
        )
    counts = ("n_cameras", "n_points", "n_observations")
    header = _convert(path, lines, tokens[:3], 0, np.int64, "header", counts)
    for k, what in enumerate(counts):
        if header[k] < 0:
            raise FormatError(
                path,
                _line_of(lines, k),
                f"header: expected a non-negative {what}, found {header[k]}",
            )
    n_cam, n_pt, n_obs = (int(v) for v in header)
    sections = [
        ("observations 'camera point u v'", 4 * n_obs),
        ("camera parameters (9 per camera)", 9 * n_cam),
        ("point coordinates (3 per point)", 3 * n_pt),
    ]
    total = 3 + sum(n for _, n in sections)
    if len(tokens) < total:
        start = 3
        for what, n in sections:
            if len(tokens) < start + n:
                raise FormatError(
                    path,
                    _line_of(lines, len(tokens)),
                    f"expected {n} {what} as the header '{n_cam} {n_pt} {n_obs}' says, "
                    f"found the end of the file after {len(tokens) - start}",
                )
            start += n
    if len(tokens) > total:
        raise FormatError(
            path,
            _line_of(lines, total),
            f"expected the end of the file after {total} values (header "
            f"'{n_cam} {n_pt} {n_obs}'), found more: {tokens[total]!r}",
        )

    o = 3
    obs_tokens = tokens[o : o + 4 * n_obs]
    cams = _convert_strided(path, lines, obs_tokens, o, 0, "camera index")
    pts = _convert_strided(path, lines, obs_tokens, o, 1, "point index")
    for idx, n, col, what in ((cams, n_cam, 0, "camera"), (pts, n_pt, 1, "point")):
        bad = np.flatnonzero((idx < 0) | (idx >= n))
        if bad.size:
            r = int(bad[0])
            raise FormatError(
                path,
                _line_of(lines, o + 4 * r + col),
                f"observation {r}: expected a {what} index in [0, {n}), found {idx[r]}",
            )
    fields = ("camera", "point", "u", "v")  # the indices are integers, so they parse too
    uv = _convert(path, lines, obs_tokens, o, np.float64, "observation", fields)
    uv = uv.reshape(n_obs, 4)[:, 2:]
    _finite(path, lines, uv, o, 4, 2, "observation", ("u", "v"))
    o += 4 * n_obs
    names = ("rx", "ry", "rz", "tx", "ty", "tz", "f", "k1", "k2")
    cameras = _convert(path, lines, tokens[o : o + 9 * n_cam], o, np.float64, "camera", names)
    cameras = cameras.reshape(n_cam, 9)
    _finite(path, lines, cameras, o, 9, 0, "camera", names)
    o += 9 * n_cam
    xyz = ("x", "y", "z")
    points = _convert(path, lines, tokens[o : o + 3 * n_pt], o, np.float64, "point", xyz)
    points = points.reshape(n_pt, 3)
    _finite(path, lines, points, o, 3, 0, "point", xyz)
    return BALProblem(
        cameras=cameras,
        points=points,
        camera_index=cams,
        point_index=pts,
        observations=uv,
        path=os.fspath(path),
    )


def _convert_strided(
    path: PathLike, lines: list[str], block: list[str], start: int, col: int, what: str
) -> np.ndarray:
    """Integer column ``col`` of a block of 4-token records starting at file token ``start``."""
    column = block[col::4]
    try:
        return np.array(column, dtype=np.int64).reshape(len(column))
    except (ValueError, OverflowError):
        pass
    for r, tok in enumerate(column):
        try:
            np.array([tok], dtype=np.int64)
        except (ValueError, OverflowError):
            line = _line_of(lines, start + 4 * r + col)
            msg = f"observation {r}: expected an integer {what}, found {tok!r}"
            raise FormatError(path, line, msg) from None
    raise AssertionError("unreachable: conversion failed but no bad token found")


def _finite(
    path: PathLike,
    lines: list[str],
    values: np.ndarray,
    start: int,
    stride: int,
    offset: int,
    what: str,
    names: tuple[str, ...],
) -> None:
    """Raise at the line of the first non-finite entry of a (rows, len(names)) block."""
    bad = ~np.isfinite(values)
    if bad.any():
        r, c = (int(v) for v in np.argwhere(bad)[0])
        line = _line_of(lines, start + stride * r + offset + c)
        raise FormatError(
            path, line, f"{what} {r}: expected a finite {names[c]}, found {values[r, c]}"
        )


# ----------------------------------------------------------------------------- writing


def write_bal(path: PathLike, problem: BALProblem) -> None:
    """Write ``problem`` in BAL layout (full float precision: reading it back is exact).

    Raises:
        ValueError: before the file is opened, if a camera, point or observation is not
            finite (:func:`read_bal` would reject the file).
    """
    for name, arr in (
        ("cameras", problem.cameras),
        ("points", problem.points),
        ("observations", problem.observations),
    ):
        refuse_nonfinite_rows(arr, f"write_bal(problem.{name})", "read_bal")
    out = [f"{problem.n_cameras} {problem.n_points} {problem.n_observations}"]
    out += [
        f"{c} {p} {u!r} {v!r}"
        for c, p, (u, v) in zip(
            problem.camera_index.tolist(),
            problem.point_index.tolist(),
            problem.observations.tolist(),
        )
    ]
    out += map(repr, problem.cameras.reshape(-1).tolist())
    out += map(repr, problem.points.reshape(-1).tolist())
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")
