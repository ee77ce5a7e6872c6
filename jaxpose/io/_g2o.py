"""g2o pose graphs: :class:`PoseGraph`, :func:`read_g2o`, :func:`write_g2o`.

Supported lines (anything else is skipped; unknown ``VERTEX*``/``EDGE*`` tags raise a warning
because dropping them changes the problem)::

    VERTEX_SE3:QUAT id x y z qx qy qz qw
    EDGE_SE3:QUAT   i j x y z qx qy qz qw  I11 I12 .. I16 I22 .. I66   (21 values)
    VERTEX_SE2      id x y θ
    EDGE_SE2        i j dx dy dθ  I11 I12 I13 I22 I23 I33              (6 values)
    FIX             id [id ...]
    # comment

Information matrices are given as the row-major upper triangle, tangent order translation
first: ``(x, y, z, rx, ry, rz)`` for SE3 and ``(x, y, θ)`` for SE2, the same order as the
``se3``/``se2`` algebras, so they weight the residual ``Log(Z⁻¹·Xi⁻¹·Xj)`` unchanged.

Poses use jaxpose storage: SE3 ``[tx, ty, tz, qx, qy, qz, qw]`` (quaternions normalised on
read) and SE2 ``[tx, ty, cos θ, sin θ]``.
"""

from __future__ import annotations

import os
import warnings
from collections import deque
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components as components

from .._checks import set_numpy_field
from ..lie._numpy import compose1, identity, inverse, normalize
from ._errors import FormatError
from ._text import describe_bad_char, first_bad_char, read_text, refuse_nonfinite_rows

__all__ = [
    "INFORMATION_POLICIES",
    "PoseGraph",
    "apply_information_policy",
    "connected_components",
    "read_g2o",
    "write_g2o",
]

PathLike = str | os.PathLike[str]

# kind -> (storage dim, tangent dim)
_DIMS = {"SE3": (7, 6), "SE2": (4, 3)}
_VERTEX_TAG = {"SE3": "VERTEX_SE3:QUAT", "SE2": "VERTEX_SE2"}
_EDGE_TAG = {"SE3": "EDGE_SE3:QUAT", "SE2": "EDGE_SE2"}
_TINY = float(np.finfo(np.float64).tiny)  # a quaternion with no component this large is zero


def _info_names(axes: tuple[str, ...]) -> list[str]:
    d = len(axes)
    return [f"I[{axes[r]},{axes[c]}]" for r in range(d) for c in range(r, d)]


# tag -> (kind, role, value field names after the ids); line layout: tag, ids, values
_SPECS: dict[str, tuple[str, str, list[str]]] = {
    "VERTEX_SE3:QUAT": ("SE3", "vertex", ["x", "y", "z", "qx", "qy", "qz", "qw"]),
    "EDGE_SE3:QUAT": (
        "SE3",
        "edge",
        ["x", "y", "z", "qx", "qy", "qz", "qw", *_info_names(("x", "y", "z", "rx", "ry", "rz"))],
    ),
    "VERTEX_SE2": ("SE2", "vertex", ["x", "y", "theta"]),
    "EDGE_SE2": ("SE2", "edge", ["dx", "dy", "dtheta", *_info_names(("x", "y", "theta"))]),
}


_LAYOUT = {
    "VERTEX_SE3:QUAT": "VERTEX_SE3:QUAT id x y z qx qy qz qw",
    "EDGE_SE3:QUAT": "EDGE_SE3:QUAT i j x y z qx qy qz qw + 21 information values",
    "VERTEX_SE2": "VERTEX_SE2 id x y theta",
    "EDGE_SE2": "EDGE_SE2 i j dx dy dtheta + 6 information values",
}


def _empty_index() -> np.ndarray:
    return np.zeros(0, np.int64)


@dataclass(frozen=True, eq=False, repr=False)
class PoseGraph:
    """A pose graph read from (or written to) a g2o file; plain float64/int64 numpy arrays.

    Attributes:
        kind: ``"SE3"`` or ``"SE2"``.
        vertex_ids: (n,) int64 ids as in the file (file order; sorted for edges-only files).
        poses: (n, 7) SE3 ``[tx,ty,tz,qx,qy,qz,qw]`` or (n, 4) SE2 ``[tx,ty,cos θ,sin θ]``.
        edges: (m, 2) int64 indices into ``poses`` (not ids), ``(i, j)``.
        measurements: (m, 7) or (m, 4) ``Z_ij``, same layouts; residual ``Log(Z⁻¹·Xi⁻¹·Xj)``.
        information: (m, 6, 6) or (m, 3, 3) symmetric positive definite, translation first.
        path: the file it was read from, if any.
        fixed: (k,) int64 indices of vertices named on ``FIX`` lines (empty if none).
    """

    kind: str
    vertex_ids: np.ndarray
    poses: np.ndarray
    edges: np.ndarray
    measurements: np.ndarray
    information: np.ndarray
    path: str | None = None
    fixed: np.ndarray = field(default_factory=_empty_index)

    def __post_init__(self) -> None:
        if self.kind not in _DIMS:
            raise ValueError(f"PoseGraph.kind: expected 'SE3' or 'SE2', got {self.kind!r}")
        d, t = _DIMS[self.kind]
        set_ = lambda name, value: object.__setattr__(self, name, value)
        check = partial(set_numpy_field, self, unwrap=True)  # groups: their stored array
        check("vertex_ids", np.int64, (None,))
        n = self.vertex_ids.shape[0]
        check("poses", np.float64, (n, d))
        check("edges", np.int64, (None, 2))
        m = self.edges.shape[0]
        check("measurements", np.float64, (m, d))
        check("information", np.float64, (m, t, t))
        check("fixed", np.int64, (None,))
        if self.path is not None:
            set_("path", os.fspath(self.path))
        for name in ("edges", "fixed"):
            idx = getattr(self, name)
            if idx.size and (idx.min() < 0 or idx.max() >= n):
                raise ValueError(f"PoseGraph.{name}: indices must lie in [0, {n}), got {idx}")

    @property
    def n_poses(self) -> int:
        """Number of vertices n."""
        return int(self.poses.shape[0])

    @property
    def n_edges(self) -> int:
        """Number of edges m."""
        return int(self.edges.shape[0])

    def __repr__(self) -> str:
        return (
            f"PoseGraph(kind={self.kind!r}, n_poses={self.n_poses}, n_edges={self.n_edges}, "
            f"fixed={self.fixed.tolist()}, path={self.path!r})"
        )


# ----------------------------------------------------------------------------- reading


def _convert(
    path: PathLike, rows: list[list[str]], lines: list[int], dtype: Any, tag: str, names: list[str]
) -> np.ndarray:
    """(len(rows), len(names)) array from token rows; a bad token raises FormatError naming
    its line and field."""
    if not rows:
        return np.zeros((0, len(names)), dtype)
    try:
        return np.array(rows, dtype=dtype).reshape(len(rows), len(names))
    except (ValueError, OverflowError):
        pass
    what = "an integer" if dtype is np.int64 else "a number"
    for row, ln in zip(rows, lines):
        for name, tok in zip(names, row):
            try:
                np.array([tok], dtype=dtype)
            except (ValueError, OverflowError):
                msg = f"{tag}: expected {what} for {name}, found {tok!r}"
                raise FormatError(path, ln, msg) from None
    raise AssertionError("unreachable: conversion failed but no bad token found")


def _check_finite(
    path: PathLike, values: np.ndarray, lines: list[int], tag: str, names: list[str]
) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise FormatError(
            path, lines[r], f"{tag}: expected a finite value for {names[c]}, found {values[r, c]}"
        )


def _unit_quaternions(path: PathLike, q: np.ndarray, lines: list[int], tag: str) -> np.ndarray:
    """Finite (k, 4) quaternions normalised scale-safely (1e200 and 1e-200 ones included);
    one whose components are all zero (or subnormal: no direction) raises FormatError."""
    bad = np.flatnonzero(np.max(np.abs(q), axis=-1) < _TINY)
    if bad.size:
        r = bad[0]
        raise FormatError(
            path,
            lines[r],
            f"{tag}: expected a non-zero quaternion (qx qy qz qw; it is normalised on read), "
            f"found {q[r].tolist()}",
        )
    return normalize(q)


def _poses_from_values(kind: str, v: np.ndarray) -> np.ndarray:
    """(k, 7) SE3 from [t, q] (already normalised) or (k, 4) SE2 from [x, y, θ]."""
    if kind == "SE3":
        return v
    return np.stack([v[:, 0], v[:, 1], np.cos(v[:, 2]), np.sin(v[:, 2])], -1)


INFORMATION_POLICIES = ("strict", "repair", "isotropic")
"""Policies for information matrices that are not positive definite
(:func:`apply_information_policy`, ``read_g2o(information=...)``)."""
_REPAIR_FLOOR = 1e-6  # repaired eigenvalues ≥ this × the largest |eigenvalue| of the edge


def _not_positive_definite(info: np.ndarray) -> np.ndarray:
    """Indices of the (m, t, t) symmetric matrices whose Cholesky factorisation fails."""
    try:
        np.linalg.cholesky(info)
        return np.zeros(0, np.int64)
    except np.linalg.LinAlgError:
        pass
    bad = []
    for e in range(info.shape[0]):
        try:
            np.linalg.cholesky(info[e])
        except np.linalg.LinAlgError:
            bad.append(e)
    return np.asarray(bad, np.int64)


def _repaired(info: np.ndarray) -> np.ndarray:
    """Nearest positive-definite matrices by eigenvalue clipping: each eigenvalue raised to
    at least ``1e-6 · max |eigenvalue|`` of its matrix (1e-6 for an all-zero matrix)."""
    w, v = np.linalg.eigh(info)
    scale = np.max(np.abs(w), axis=-1, keepdims=True)
    floor = _REPAIR_FLOOR * np.where(scale > 0, scale, 1.0)
    w = np.maximum(w, floor)
    out = (v * w[..., None, :]) @ np.swapaxes(v, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def _isotropic(info: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SE-Sync's trace-based weights; returns (matrices, indices of edges without valid
    weights). SE3: ``τ = 3/tr(Ω_tt⁻¹)``, ``κ = 3/(2·tr(Ω_RR⁻¹))``, Ω = diag(τ·I₃, 2κ·I₃);
    SE2: ``τ = 2/tr(Ω_tt⁻¹)``, Ω = diag(τ, τ, Ω_θθ)."""
    t = info.shape[-1]
    dt = t // 2 + (t == 3)  # translation block size: 3 of 6, 2 of 3
    with np.errstate(all="ignore"):
        tt = info[:, :dt, :dt]
        tau = dt / np.trace(np.linalg.pinv(tt, hermitian=True), axis1=1, axis2=2)
        if t == 6:
            rr = np.linalg.pinv(info[:, 3:, 3:], hermitian=True)
            rot = 2.0 * (3.0 / (2.0 * np.trace(rr, axis1=1, axis2=2)))  # 2κ
            diag = np.concatenate([np.repeat(tau[:, None], 3, 1), np.repeat(rot[:, None], 3, 1)], 1)
        else:
            diag = np.stack([tau, tau, info[:, 2, 2]], 1)
    bad = np.flatnonzero(~np.all(np.isfinite(diag) & (diag > 0), axis=1))
    out = np.zeros_like(info)
    idx = np.arange(t)
    out[:, idx, idx] = diag
    return out, bad


def apply_information_policy(information: Any, policy: str = "strict") -> np.ndarray:
    """Information matrices ``(m, t, t)`` under a policy for non-positive-definite ones.

    * ``"strict"``: returned unchanged (as float64, symmetrised); ``ValueError`` if any is
      not positive definite (the message names the other policies).
    * ``"repair"``: the matrices that are not positive definite are replaced by the nearest
      positive-definite matrix by eigenvalue clipping (eigenvalues raised to at least 1e-6
      times the largest absolute eigenvalue of that matrix); the others are unchanged.
    * ``"isotropic"``: every matrix becomes SE-Sync's isotropic rotation/translation weight
      (Rosen et al., IJRR 2019): SE3 ``diag(τ·I₃, 2κ·I₃)`` with ``τ = 3/tr(Ω_tt⁻¹)``,
      ``κ = 3/(2·tr(Ω_RR⁻¹))`` (2κ weights the tangent rotation error, since
      ``‖R_j − R_i Z‖²_F ≈ 2|φ|²``); SE2 ``diag(τ, τ, Ω_θθ)`` with ``τ = 2/tr(Ω_tt⁻¹)``.
      Blocks whose trace-based weight is not positive raise ``ValueError``.

    ``t`` is 6 (SE3, translation first) or 3 (SE2).
    ``"repair"`` warns with the count and the first edge indices it changed.
    """
    info, _ = _apply_policy(information, policy, "apply_information_policy")
    return info


def _apply_policy(information: Any, policy: str, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(matrices, indices of the non-positive-definite input matrices) or ValueError."""
    if policy not in INFORMATION_POLICIES:
        raise ValueError(f"{where}(information={policy!r}): expected one of {INFORMATION_POLICIES}")
    info = np.asarray(information, np.float64)
    if info.ndim != 3 or info.shape[1] != info.shape[2] or info.shape[1] not in (3, 6):
        raise ValueError(
            f"{where}: expected information of shape (m, 6, 6) or (m, 3, 3), got {info.shape}"
        )
    info = 0.5 * (info + np.swapaxes(info, -1, -2))
    bad = (
        _not_positive_definite(info)
        if np.all(np.isfinite(info))
        else np.flatnonzero(~np.all(np.isfinite(info), axis=(1, 2)))
    )
    if policy == "repair" and bad.size:
        shown = ", ".join(map(str, bad[:5].tolist())) + (", ..." if bad.size > 5 else "")
        warnings.warn(
            f"{where}: {bad.size} of {info.shape[0]} information matrices are not positive "
            f"definite; repaired by eigenvalue clipping (edges {shown})",
            stacklevel=3,
        )
        info = info.copy()
        info[bad] = _repaired(np.nan_to_num(info[bad], nan=0.0, posinf=0.0, neginf=0.0))
    elif policy == "isotropic":
        info, wrong = _isotropic(info)
        if wrong.size:
            raise ValueError(
                f"{where}(information='isotropic'): edge {wrong[0]} (and {wrong.size - 1} "
                "more) has a translation or rotation block whose trace-based weight is not "
                "positive; use information='repair'"
            )
    elif policy == "strict" and bad.size:
        raise ValueError(
            f"{where}: {bad.size} of {info.shape[0]} information matrices are not positive "
            f"definite (first: edge {bad[0]}); use information='repair' (nearest positive "
            "definite) or 'isotropic' (SE-Sync's trace-based weights)"
        )
    return info, bad


def _information(
    path: PathLike,
    upper: np.ndarray,
    lines: list[int],
    tag: str,
    ids: np.ndarray,
    policy: str = "strict",
) -> np.ndarray:
    """(m, t, t) symmetric matrices from row-major upper triangles, checked by Cholesky and
    handled by ``policy`` (:func:`apply_information_policy`)."""
    m, k = upper.shape
    t = int(round((np.sqrt(8 * k + 1) - 1) / 2))
    r, c = np.triu_indices(t)
    info = np.zeros((m, t, t))
    info[:, r, c] = upper
    info[:, c, r] = upper
    bad = _not_positive_definite(info)
    if not bad.size and policy != "isotropic":
        return info
    if policy == "strict":
        e = bad[0]
        eig = np.linalg.eigvalsh(info[e])
        raise FormatError(
            path,
            lines[e],
            f"{tag} {ids[e, 0]} {ids[e, 1]} (edge {e}): expected a symmetric positive "
            f"definite information matrix, found one whose Cholesky factorisation fails "
            f"(smallest eigenvalue {eig[0]:.6g}; {bad.size} of {m} edges are not positive "
            "definite). Read the file with information='repair' (nearest positive-definite "
            "matrix per edge) or information='isotropic' (SE-Sync's trace-based weights); "
            "CLI: --information repair|isotropic",
        )
    if policy == "isotropic":
        out, wrong = _isotropic(info)
        if wrong.size:
            e = wrong[0]
            raise FormatError(
                path,
                lines[e],
                f"{tag} {ids[e, 0]} {ids[e, 1]} (edge {e}): information='isotropic' needs "
                "translation and rotation blocks with a positive trace-based weight "
                f"({wrong.size} edges have none); use information='repair'",
            )
        return out
    shown = ", ".join(str(lines[e]) for e in bad[:5]) + (", ..." if bad.size > 5 else "")
    warnings.warn(
        f"{os.fspath(path)}: {bad.size} of {m} information matrices are not positive "
        f"definite; repaired by eigenvalue clipping (lines {shown})",
        stacklevel=3,
    )
    info = info.copy()
    info[bad] = _repaired(info[bad])
    return info


def _index_of(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted ids and the permutation mapping sorted positions to original indices."""
    order = np.argsort(ids, kind="stable")
    return ids[order], order


def _lookup(sorted_ids: np.ndarray, order: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Indices of ``query`` ids; -1 where absent."""
    pos = np.clip(np.searchsorted(sorted_ids, query), 0, max(len(sorted_ids) - 1, 0))
    if not len(sorted_ids):
        return np.full(query.shape, -1, np.int64)
    found = sorted_ids[pos] == query
    return np.where(found, order[pos], -1)


def read_g2o(path: PathLike, *, kind: str | None = None, information: str = "strict") -> PoseGraph:
    """Read a g2o pose graph (SE3 or SE2).

    Args:
        path: file to read.
        kind: ``"SE3"`` or ``"SE2"`` to require that kind; by default it is inferred from the
            tags (a file mixing SE2 and SE3 tags is an error).
        information: policy for information matrices that are not positive definite
            (:func:`apply_information_policy`): ``"strict"`` (an error naming the other two),
            ``"repair"`` (nearest positive-definite matrix per such edge, with a warning
            giving their count and first lines) or ``"isotropic"`` (every edge gets SE-Sync's
            trace-based rotation/translation weights).

    Returns:
        A :class:`PoseGraph`. Quaternions are normalised scale-safely (``1e200`` or ``1e-200``
        times a unit quaternion reads as that unit quaternion; all-zero ones are rejected); SE2
        angles become ``(cos θ, sin θ)``; ``FIX id`` lines are collected in ``fixed``.

    The text is UTF-8; a byte-order mark at the start is dropped. Numbers on pose-graph lines
    must be spelled in ASCII: ``1_0``, non-ASCII digits (``١``, ``１``) and non-ASCII spaces
    are rejected, although Python's ``int``/``float`` would accept them. Comment lines
    (``#``) and skipped lines may hold any text.

    Files with edges but no ``VERTEX`` lines (e.g. manhattan.g2o) get vertices for every id
    named by an edge (``vertex_ids`` sorted ascending) and initial poses from the measurements:
    the smallest id starts at the identity; whenever a vertex is set, the odometry chain from
    it (edges ``id → id+1``, the first such edge in file order) is followed as far as it
    goes; vertices still unset are then reached breadth-first over any edge (edges traversed
    backwards use ``Z⁻¹``), starting from the earliest set vertices. If the edges form several
    disconnected pieces, each further piece starts at the identity at its smallest id and a
    warning says so (the solver needs a fixed pose or prior in each piece).

    Raises:
        FormatError: ``"FILE:LINE: ..."`` for a wrong number of values, non-numeric or
            non-finite values, non-ASCII or ``_`` characters in them, invalid UTF-8, zero
            quaternions, duplicate vertex ids, self-loop edges (``i == j``), edges or FIX
            lines naming missing vertices, information matrices that are not positive
            definite (with ``information="strict"``), SE2/SE3 tags mixed (or not the
            requested ``kind``), a byte-order mark after the first line, edges-only initial
            poses beyond the float64 range, or no pose-graph lines.
        OSError: the file cannot be read.
    """
    if kind is not None and kind not in _DIMS:
        raise ValueError(f"read_g2o: kind must be 'SE3', 'SE2' or None, got {kind!r}")
    if information not in INFORMATION_POLICIES:
        raise ValueError(
            f"read_g2o(information={information!r}): expected one of {INFORMATION_POLICIES}"
        )
    text = read_text(path)  # a leading byte-order mark is dropped
    lines = text.split("\n")
    rows: dict[str, list[list[str]]] = {"vertex": [], "edge": []}
    row_lines: dict[str, list[int]] = {"vertex": [], "edge": []}
    fix_rows: list[tuple[int, list[str]]] = []
    unknown: dict[str, tuple[int, int]] = {}
    seen: tuple[str, int] | None = None  # (tag, line) that set the kind
    for ln, raw in enumerate(lines, 1):
        toks = raw.split()
        if not toks or toks[0].startswith("#"):
            continue
        tag = toks[0]
        spec = _SPECS.get(tag)
        if spec is None and tag.startswith("\ufeff"):
            raise FormatError(
                path,
                ln,
                f"expected a tag, found a byte-order mark U+FEFF before {tag[1:]!r} "
                "(only the first line may start with one: concatenated files?)",
            )
        if spec is None:
            if tag == "FIX":
                if len(toks) < 2:
                    raise FormatError(path, ln, "FIX: expected 'FIX id [id ...]', found no id")
                body = raw.lstrip()[len(tag) :]
                bad = first_bad_char(body)
                if bad >= 0:
                    found = describe_bad_char(body, bad)[1]
                    raise FormatError(path, ln, f"FIX: expected an integer id, {found}")
                fix_rows.append((ln, toks[1:]))
            elif tag.startswith(("VERTEX", "EDGE")):
                first, count = unknown.get(tag, (ln, 0))
                unknown[tag] = (first, count + 1)
            continue
        tag_kind, role, names = spec
        if kind is None:
            kind, seen = tag_kind, (tag, ln)
        elif tag_kind != kind:
            why = f"line {seen[1]} has {seen[0]}" if seen else f"kind={kind!r} was requested"
            raise FormatError(
                path, ln, f"expected {kind} tags only ({why}), found {tag}: SE2 and SE3 mixed"
            )
        n_ids = 1 if role == "vertex" else 2
        if len(toks) != 1 + n_ids + len(names):
            raise FormatError(
                path,
                ln,
                f"expected {n_ids + len(names)} values after {tag} ({_LAYOUT[tag]}), "
                f"found {len(toks) - 1}",
            )
        body = raw.lstrip()[len(tag) :]
        bad = first_bad_char(body)
        if bad >= 0:
            field, found = describe_bad_char(body, bad)
            fields = ["id"] if role == "vertex" else ["i", "j"]
            fields += names
            raise FormatError(
                path,
                ln,
                f"{tag}: expected a number for {fields[min(field, len(fields) - 1)]}, {found}",
            )
        rows[role].append(toks[1:])
        row_lines[role].append(ln)

    if unknown:
        listed = ", ".join(f"{t} ({c}x, first on line {f})" for t, (f, c) in unknown.items())
        warnings.warn(f"{os.fspath(path)}: skipped unsupported lines: {listed}", stacklevel=2)
    if not rows["vertex"] and not rows["edge"]:
        raise FormatError(
            path,
            max(1, len(lines) - (lines[-1] == "")),
            "expected VERTEX_SE3:QUAT/EDGE_SE3:QUAT or VERTEX_SE2/EDGE_SE2 lines, found none",
        )
    assert kind is not None
    t = _DIMS[kind][1]
    vtag, etag = _VERTEX_TAG[kind], _EDGE_TAG[kind]
    vnames, enames = _SPECS[vtag][2], _SPECS[etag][2]
    n_meas = len(enames) - t * (t + 1) // 2

    # vertices
    vrows, vlines = rows["vertex"], row_lines["vertex"]
    vids = _convert(path, [r[:1] for r in vrows], vlines, np.int64, vtag, ["id"])[:, 0]
    vvals = _convert(path, [r[1:] for r in vrows], vlines, np.float64, vtag, vnames)
    _check_finite(path, vvals, vlines, vtag, vnames)
    if kind == "SE3":
        vvals = np.concatenate(
            [vvals[:, :3], _unit_quaternions(path, vvals[:, 3:], vlines, vtag)], 1
        )
    sorted_ids, order = _index_of(vids)
    dup = np.flatnonzero(sorted_ids[1:] == sorted_ids[:-1])
    if dup.size:
        later = [order[k + 1] for k in dup]  # stable sort: order[k] precedes order[k + 1]
        k = dup[int(np.argmin(later))]
        raise FormatError(
            path,
            vlines[order[k + 1]],
            f"{vtag}: expected unique vertex ids, found id {sorted_ids[k]} again "
            f"(first defined on line {vlines[order[k]]})",
        )

    # edges
    erows, elines = rows["edge"], row_lines["edge"]
    eids = _convert(path, [r[:2] for r in erows], elines, np.int64, etag, ["i", "j"])
    loops = np.flatnonzero(eids[:, 0] == eids[:, 1])
    if loops.size:
        e = int(loops[0])
        raise FormatError(
            path,
            elines[e],
            f"{etag} {eids[e, 0]} {eids[e, 1]}: expected an edge between two different "
            "vertices, found a self-loop (its residual Log(Z⁻¹) does not depend on the pose)",
        )
    evals = _convert(path, [r[2:] for r in erows], elines, np.float64, etag, enames)
    _check_finite(path, evals, elines, etag, enames)
    meas = evals[:, :n_meas]
    if kind == "SE3":
        meas = np.concatenate([meas[:, :3], _unit_quaternions(path, meas[:, 3:], elines, etag)], 1)
    meas = _poses_from_values(kind, meas)

    # fixed ids
    fix_ids: list[int] = []
    fix_lines: list[int] = []
    for ln, toks in fix_rows:
        ids_ = _convert(path, [toks], [ln], np.int64, "FIX", ["id"] * len(toks))
        fix_ids.extend(ids_[0].tolist())
        fix_lines.extend([ln] * len(toks))
    fix_arr = np.asarray(fix_ids, np.int64)

    if vrows:
        edges = _lookup(sorted_ids, order, eids)
        missing = np.argwhere(edges < 0)
        if missing.size:
            e, side = missing[0]
            raise FormatError(
                path,
                elines[e],
                f"{etag} {eids[e, 0]} {eids[e, 1]}: expected vertex {eids[e, side]} to be "
                f"defined by a {vtag} line, found none",
            )
        fixed = _lookup(sorted_ids, order, fix_arr)
        poses = _poses_from_values(kind, vvals)
        vertex_ids = vids
    else:
        vertex_ids = np.unique(eids)
        edges = np.searchsorted(vertex_ids, eids).reshape(-1, 2)
        fixed = _lookup(vertex_ids, np.arange(len(vertex_ids)), fix_arr)
        poses = None
    if (fixed < 0).any():
        k = int(np.flatnonzero(fixed < 0)[0])
        where = f"a {vtag} line" if vrows else "an edge"
        raise FormatError(
            path,
            fix_lines[k],
            f"FIX: expected vertex {fix_arr[k]} to be defined by {where}, found none",
        )
    fixed = np.asarray(list(dict.fromkeys(fixed.tolist())), np.int64)
    info = _information(path, evals[:, n_meas:], elines, etag, eids, information)

    if poses is None:
        with np.errstate(over="ignore", invalid="ignore"):
            poses, n_components, via = _initialise(kind, vertex_ids, edges, meas)
        bad = np.flatnonzero(~np.isfinite(poses).all(axis=1))
        if bad.size:  # huge translations chained past the float64 range
            e = int(via[bad[0]])
            raise FormatError(
                path,
                elines[e],
                f"{etag} {eids[e, 0]} {eids[e, 1]}: chaining the measurements to vertex "
                f"{vertex_ids[bad[0]]} gives a non-finite initial pose (translations beyond the "
                "float64 range); give VERTEX lines with initial poses",
            )
        if n_components > 1:
            warnings.warn(
                f"{os.fspath(path)}: the edges form {n_components} disconnected pieces; each "
                "piece after the first starts at the identity at its smallest vertex id",
                stacklevel=2,
            )
    return PoseGraph(
        kind=kind,
        vertex_ids=vertex_ids,
        poses=poses,
        edges=edges,
        measurements=meas,
        information=info,
        path=os.fspath(path),
        fixed=fixed,
    )


def _adjacency(n: int, edges: np.ndarray) -> list[list[tuple[int, int, bool]]]:
    """Per vertex, ``(edge, neighbour, forward)`` in edge order; forward means vertex is i."""
    adj: list[list[tuple[int, int, bool]]] = [[] for _ in range(n)]
    for e, (i, j) in enumerate(edges.tolist()):
        adj[i].append((e, j, True))
        adj[j].append((e, i, False))
    return adj


def _initialise(
    kind: str, vertex_ids: np.ndarray, edges: np.ndarray, meas: np.ndarray
) -> tuple[np.ndarray, int, np.ndarray]:
    """Initial poses for an edges-only graph (see :func:`read_g2o`); returns (poses, pieces,
    via): ``via[v]`` is the edge that set vertex v (-1 for the start of a piece)."""
    n = len(vertex_ids)
    ids = vertex_ids.tolist()
    ends = edges.tolist()
    odometry: dict[int, int] = {}
    for e, (i, j) in enumerate(ends):
        if ids[j] == ids[i] + 1 and i not in odometry:
            odometry[i] = e
    adj = _adjacency(n, edges)
    forward = meas.tolist()
    backward = inverse(kind, meas).tolist()
    poses: list[list[float] | None] = [None] * n
    via = np.full(n, -1, np.int64)
    queue: deque[int] = deque()

    def settle(v: int, pose: list[float], edge: int) -> None:
        while True:
            poses[v] = pose
            via[v] = edge
            queue.append(v)
            e = odometry.get(v)
            if e is None or poses[ends[e][1]] is not None:
                return
            v, pose, edge = ends[e][1], compose1(kind, pose, forward[e]), e

    pieces = 0
    for start in range(n):  # vertex_ids is sorted, so this is smallest id first
        if poses[start] is not None:
            continue
        pieces += 1
        settle(start, identity(kind).tolist(), -1)
        while queue:
            v = queue.popleft()
            for e, w, fwd in adj[v]:
                if poses[w] is None:
                    settle(w, compose1(kind, poses[v], forward[e] if fwd else backward[e]), e)
    return np.asarray(poses, np.float64).reshape(n, _DIMS[kind][0]), pieces, via


def connected_components(graph: PoseGraph) -> np.ndarray:
    """(n,) int64 label per vertex; vertices joined by edges (either direction) share a label.

    Labels are 0, 1, ... in order of each piece's first vertex. A solver needs one fixed pose
    (or a prior) per piece.
    """
    n = graph.n_poses
    edges = np.asarray(graph.edges, np.int64).reshape(-1, 2)
    adjacency = scipy.sparse.coo_matrix(
        (np.ones(edges.shape[0]), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, raw = components(adjacency, directed=False)
    _, first = np.unique(raw, return_index=True)  # first vertex of each piece
    rank = np.empty(first.size, np.int64)
    rank[np.argsort(first)] = np.arange(first.size)
    return rank[raw]


# ----------------------------------------------------------------------------- writing


def _fmt(values: list[float]) -> str:
    return " ".join(map(repr, values))  # shortest text that reads back to the same float


def _check_writable_graph(graph: PoseGraph, poses: np.ndarray) -> None:
    """Raise ValueError for what read_g2o would reject (see write_g2o)."""
    ids = graph.vertex_ids
    if ids.size == 0:
        raise ValueError("write_g2o(graph): the graph has no vertices (an empty file); "
                         "read_g2o would reject the file")
    rot = slice(3, 7) if graph.kind == "SE3" else slice(2, 4)
    what = "quaternion" if graph.kind == "SE3" else "(cos θ, sin θ)"
    for name, arr, label in (
        ("poses", poses, lambda k: f"vertex id {ids[k]}"),
        ("graph.measurements", graph.measurements, lambda k: f"edge {k}"),
    ):
        refuse_nonfinite_rows(arr, f"write_g2o({name})", "read_g2o", label)
        bad = np.flatnonzero(np.max(np.abs(arr[:, rot]), axis=1) < _TINY)
        if bad.size:
            k = int(bad[0])
            raise ValueError(
                f"write_g2o({name}): row {k} ({label(k)}) has a zero {what} "
                f"{arr[k, rot].tolist()}; read_g2o would reject the file"
            )
    # the file holds the upper triangle: an asymmetric matrix would come back changed
    # (the tolerance of graph.Factor's check: rounding-level asymmetry is harmless)
    asym = np.flatnonzero(~np.all(np.isclose(graph.information,
                                             np.swapaxes(graph.information, 1, 2),
                                             rtol=1e-9, atol=1e-12), axis=(1, 2)))
    if asym.size:
        e = int(asym[0])
        raise ValueError(
            f"write_g2o(graph.information): matrix {e} is not symmetric "
            f"{graph.information[e].tolist()}; the file holds its upper triangle, so "
            "read_g2o would return a different matrix (symmetrise it first)")
    # check the symmetric matrix read_g2o will rebuild
    t = graph.information.shape[-1]
    r, c = np.triu_indices(t)
    info = np.zeros_like(graph.information)
    info[:, r, c] = graph.information[:, r, c]
    info[:, c, r] = graph.information[:, r, c]
    if not _all_spd(info):
        e = next(e for e in range(len(info)) if not _all_spd(info[e : e + 1]))
        raise ValueError(
            f"write_g2o(graph.information): matrix {e} (its upper triangle, as written) is not "
            f"finite positive definite: {graph.information[e].tolist()}; read_g2o would reject "
            "the file"
        )
    loops = np.flatnonzero(graph.edges[:, 0] == graph.edges[:, 1])
    if loops.size:
        e = int(loops[0])
        raise ValueError(
            f"write_g2o(graph.edges): edge {e} is a self-loop on vertex id "
            f"{ids[graph.edges[e, 0]]}; read_g2o would reject the file"
        )
    uniq, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        raise ValueError(
            f"write_g2o(graph.vertex_ids): id {uniq[counts > 1][0]} appears more than once; "
            "read_g2o would reject the file"
        )


def _all_spd(m: np.ndarray) -> bool:
    """Whether every (…, t, t) symmetric matrix is finite and positive definite."""
    if not np.isfinite(m).all():
        return False
    try:
        np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        return False
    return True


def write_g2o(path: PathLike, graph: PoseGraph, poses: Any = None) -> None:
    """Write ``graph`` as a g2o file in full float precision: reading it back returns the
    written numbers, except that :func:`read_g2o` normalises quaternions (a non-unit one
    comes back normalised; a unit one may move by an ulp) and rebuilds each information
    matrix from its upper triangle.

    Args:
        path: file to write (overwritten).
        graph: the pose graph; its vertex ids, edges, measurements, information and fixed
            vertices are written.
        poses: optional (n, 7) / (n, 4) array (or jaxpose group) replacing ``graph.poses``,
            e.g. the optimised poses.

    SE2 angles are written as ``atan2(sin, cos)``; information matrices as their upper
    triangle. Vertices come first, then edges, then ``FIX`` lines (GTSAM's 2-D reader
    stops at the first line it does not know).

    Raises:
        ValueError: before the file is opened, for anything :func:`read_g2o` would reject:
            non-finite poses, measurements or information, zero quaternions (SE3) or
            ``(cos θ, sin θ) = (0, 0)`` (SE2), information matrices that are not symmetric
            or not positive definite, self-loop edges, duplicate vertex ids or a graph
            without vertices.
    """
    t = _DIMS[graph.kind][1]
    if poses is None:
        poses = graph.poses
    else:
        poses = np.asarray(getattr(poses, "data", poses), dtype=np.float64)
        if poses.shape != graph.poses.shape:
            raise ValueError(
                f"write_g2o: poses must have shape {graph.poses.shape} like graph.poses "
                f"({graph.kind} storage), got {poses.shape}"
            )
    _check_writable_graph(graph, poses)
    if graph.kind == "SE2":
        poses = np.stack([poses[:, 0], poses[:, 1], np.arctan2(poses[:, 3], poses[:, 2])], -1)
        meas = graph.measurements
        meas = np.stack([meas[:, 0], meas[:, 1], np.arctan2(meas[:, 3], meas[:, 2])], -1)
    else:
        meas = graph.measurements
    r, c = np.triu_indices(t)
    upper = graph.information[:, r, c]
    vtag, etag = _VERTEX_TAG[graph.kind], _EDGE_TAG[graph.kind]
    ids = graph.vertex_ids.tolist()
    out = [f"{vtag} {i} {_fmt(p)}" for i, p in zip(ids, poses.tolist())]
    ends = graph.vertex_ids[graph.edges].tolist()
    out += [
        f"{etag} {i} {j} {_fmt(z)} {_fmt(w)}"
        for (i, j), z, w in zip(ends, meas.tolist(), upper.tolist())
    ]
    # last: GTSAM's 2-D reader stops at the first line it does not know (a FIX line between
    # vertices and edges made it read a graph without edges)
    out += [f"FIX {ids[k]}" for k in graph.fixed.tolist()]
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")
