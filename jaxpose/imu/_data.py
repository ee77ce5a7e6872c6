"""Reader for GTSAM's IMU + GPS example stream (``imuAndGPSdata.csv``).

Rows (comma separated, first field the row type):

* ``i,N,E,D,qx,qy,qz,qw,vN,vE,vD`` — the initial state (one row, first);
* ``0,ax,ay,az,gx,gy,gz`` — an IMU sample (specific force, angular rate; body frame);
* ``1,N,E,D,qx,qy,qz,qw`` — a GPS fix, received after all IMU rows above it, whose
  orientation is ground truth.

The stream has no timestamps: GTSAM's ``ImuFactorsExample`` integrates every sample with
dt = 0.005 s and zero gravity (``MakeSharedD(0.0)``).

The initial row of the published file, ``i,0,0,0,0,0,0,0,0,0,1``, is not a valid state in
the documented layout (its quaternion would be all zeros and its velocity (0, 0, 1) m/s;
GTSAM's example turns the zero quaternion into the identity through an unnormalised
conversion and starts at 1 m/s down, which its GPS fixes then correct). The fixes in the
file equal dead reckoning of the IMU samples from rest (to their printed precision), and
the row reads as a valid state in the layout ``[p, v, q]``: position 0, velocity 0,
identity rotation. :func:`read_imu_gps` therefore uses the documented layout when its
quaternion has unit norm and ``[p, v, q]`` when only that one does, and records which in
``initial_layout``; a row valid in neither raises :class:`~jaxpose.io.FormatError`.
"""

from __future__ import annotations

import math
import os
from typing import NamedTuple

import numpy as np

from ..io._errors import FormatError
from ..io._text import describe_bad_char, first_bad_char, read_text

DT = 0.005  # sample period used by GTSAM's ImuFactorsExample for this stream [s]


class ImuGpsData(NamedTuple):
    """A parsed stream (float64 numpy arrays).

    ``acc``, ``gyro`` (N, 3): IMU samples; ``gps_index`` (K,): number of IMU samples
    received before each fix; ``gps_position`` (K, 3), ``gps_rotation`` (K, 4)
    ``[qx, qy, qz, qw]``: the fixes; ``init_position``, ``init_velocity`` (3,),
    ``init_rotation`` (4,): the initial state; ``initial_row`` (10,) its raw values;
    ``initial_layout``: ``"p,q,v"`` (documented) or ``"p,v,q"`` (module docstring)."""

    acc: np.ndarray
    gyro: np.ndarray
    gps_index: np.ndarray
    gps_position: np.ndarray
    gps_rotation: np.ndarray
    init_position: np.ndarray
    init_velocity: np.ndarray
    init_rotation: np.ndarray
    initial_row: np.ndarray
    initial_layout: str


def _floats(path: str, line: int, fields: list[str], count: int, kind: str) -> list[float]:
    if len(fields) != count:
        raise FormatError(path, line, f"{kind} row: expected {count} numbers after the "
                          f"type, found {len(fields)}")
    try:
        vals = [float(x) for x in fields]
    except ValueError:
        raise FormatError(path, line, f"{kind} row: expected numbers, found "
                          f"{','.join(fields)!r}") from None
    if not np.all(np.isfinite(vals)):
        raise FormatError(path, line, f"{kind} row: non-finite value")
    return vals


def _unit(q: np.ndarray) -> bool:
    return abs(math.hypot(*(float(v) for v in q)) - 1.0) < 1e-6  # no overflow warning


def read_imu_gps(path: str | os.PathLike[str]) -> ImuGpsData:
    """Parse an IMU + GPS stream in GTSAM's example format (module docstring).

    The text is UTF-8 (a leading byte-order mark is dropped) and must be ASCII: ``1_0``,
    non-ASCII digits and non-ASCII spaces are rejected although Python's ``float`` accepts
    them. Blank lines are skipped.

    Raises:
        FormatError: ``"FILE:LINE: ..."`` for invalid UTF-8, non-ASCII or ``_`` characters,
            an unknown row type, a wrong number of values, non-numeric or non-finite values,
            a GPS quaternion without unit norm, a misplaced or missing initial-state row, or
            no IMU rows.
        OSError: the file cannot be read.
    """
    path = os.fspath(path)
    imu: list[list[float]] = []
    gps: list[list[float]] = []
    gps_index: list[int] = []
    init: list[float] | None = None
    init_line = 1
    for k, raw in enumerate(read_text(path).split("\n"), start=1):
        line = raw.strip()
        if not line:
            continue
        bad = first_bad_char(line)
        if bad >= 0:
            _, found = describe_bad_char(line.replace(",", " "), bad)
            raise FormatError(path, k, f"expected ASCII numbers separated by commas, {found}")
        kind, *fields = line.split(",")
        if kind == "i":
            if init is not None or imu or gps:
                raise FormatError(path, k, "initial-state row 'i' must come first, once")
            init, init_line = _floats(path, k, fields, 10, "initial-state"), k
        elif kind == "0":
            imu.append(_floats(path, k, fields, 6, "IMU"))
        elif kind == "1":
            fix = _floats(path, k, fields, 7, "GPS")
            if not _unit(np.asarray(fix[3:7])):
                raise FormatError(path, k, "GPS row: quaternion [qx, qy, qz, qw] must "
                                  "have unit norm")
            gps.append(fix)
            gps_index.append(len(imu))
        else:
            raise FormatError(path, k, f"unknown row type {kind!r} (expected i, 0 or 1)")
    if init is None:
        raise FormatError(path, 1, "missing the initial-state row 'i'")
    if not imu:
        raise FormatError(path, 1, "no IMU rows (type 0)")
    row = np.asarray(init)
    if _unit(row[3:7]):
        layout, q, v = "p,q,v", row[3:7], row[7:10]
    elif _unit(row[6:10]):
        layout, q, v = "p,v,q", row[6:10], row[3:6]
    else:
        raise FormatError(path, init_line, "initial-state row: no unit quaternion at [3:7] "
                          "(N,E,D,qx,qy,qz,qw,vN,vE,vD) or [6:10] (N,E,D,vN,vE,vD,q)")
    imu_arr = np.asarray(imu)
    gps_arr = np.asarray(gps).reshape(-1, 7)
    return ImuGpsData(
        acc=imu_arr[:, 0:3], gyro=imu_arr[:, 3:6],
        gps_index=np.asarray(gps_index, dtype=np.int64),
        gps_position=gps_arr[:, 0:3], gps_rotation=gps_arr[:, 3:7],
        init_position=row[0:3].copy(), init_velocity=np.asarray(v, dtype=np.float64),
        init_rotation=np.asarray(q, dtype=np.float64), initial_row=row,
        initial_layout=layout,
    )
