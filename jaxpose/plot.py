"""Optional plotting helpers (need the ``plot`` extra: matplotlib)."""

from __future__ import annotations

from typing import Any

import numpy as np


def position_covariances(kind: str, poses: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """World-frame covariances of the pose positions (n, k, k) from pose marginals.

    ``covariances`` (n, d, d) are in jaxpose's tangent chart (right perturbation, translation
    first: se2 ``[ρx, ρy, θ]``, se3 ``[ρ, φ]``). To first order the position moves by R·ρ,
    so its covariance is R Σ_ρρ Rᵀ (k = 2 for SE2, 3 for SE3)."""
    poses = np.asarray(poses, np.float64)
    cov = np.asarray(covariances, np.float64)
    if kind == "SE2":
        c, s = poses[:, 2], poses[:, 3]
        norm = np.hypot(c, s)
        rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2) / norm[:, None, None]
        k = 2
    else:
        x, y, z, w = (poses[:, 3 + i] for i in range(4))
        rot = np.stack([
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ], -2) / (x * x + y * y + z * z + w * w)[:, None, None]
        k = 3
    return rot @ cov[:, :k, :k] @ np.swapaxes(rot, 1, 2)


def ellipse_axes(cov2: np.ndarray, sigma: float = 2.0) -> tuple[np.ndarray, ...]:
    """(width, height, angle in degrees) of the ``sigma``-σ ellipses of (n, 2, 2)
    covariances (matplotlib's ``Ellipse`` convention: full axis lengths)."""
    w, v = np.linalg.eigh(np.asarray(cov2, np.float64))
    w = np.clip(w, 0.0, None)
    angle = np.degrees(np.arctan2(v[:, 1, 1], v[:, 0, 1]))
    return 2 * sigma * np.sqrt(w[:, 1]), 2 * sigma * np.sqrt(w[:, 0]), angle


def _draw_ellipses(ax: Any, centers: np.ndarray, cov2: np.ndarray, max_count: int) -> None:
    from matplotlib.collections import EllipseCollection

    step = max(1, int(np.ceil(centers.shape[0] / max_count)))
    sel = np.arange(0, centers.shape[0], step)
    width, height, angle = ellipse_axes(cov2[sel])
    ax.add_collection(EllipseCollection(
        width, height, angle, units="xy", offsets=centers[sel], offset_transform=ax.transData,
        facecolors="none", edgecolors="tab:red", linewidths=0.6))
    reach = np.maximum(width, height)[:, None] / 2  # keep whole ellipses in view
    ax.update_datalim(np.concatenate([centers[sel] - reach, centers[sel] + reach]))
    ax.autoscale_view()


def plot_pose_graphs(path: str, kind: str, before: np.ndarray, after: np.ndarray,
                     edges: np.ndarray | None = None, title: str = "",
                     covariances: np.ndarray | None = None, max_ellipses: int = 300) -> None:
    """Save a before/after plot of pose positions (x–y; 3D graphs also x–z) to ``path``.

    With ``covariances`` (n, d, d), the pose marginals at ``after`` in jaxpose's tangent
    chart (:func:`jaxpose.graph.marginals`), the optimised panels also show 2-σ ellipses
    of the position marginals (world frame, projected onto each view; at most
    ``max_ellipses`` poses, evenly spaced)."""
    try:  # a Figure of its own (no pyplot): the caller's backend and figures stay as they are
        from matplotlib.figure import Figure
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(
            "plotting needs matplotlib: pip install 'jaxpose[plot]'"
        ) from err
    views = [(0, 1)] if kind == "SE2" else [(0, 1), (0, 2)]
    pos_cov = (None if covariances is None
               else position_covariances(kind, after, covariances))
    fig = Figure(figsize=(10, 4.5 * len(views)))
    axes = fig.subplots(len(views), 2, squeeze=False)
    for row, (a, b) in enumerate(views):
        for col, (label, poses) in enumerate((("initial", before), ("optimised", after))):
            ax: Any = axes[row][col]
            if edges is not None and len(edges) <= 20000:
                seg = np.stack([poses[edges[:, 0]][:, [a, b]], poses[edges[:, 1]][:, [a, b]]], 1)
                from matplotlib.collections import LineCollection

                ax.add_collection(LineCollection(seg, linewidths=0.2, colors="0.7"))
            ax.plot(poses[:, a], poses[:, b], lw=0.6)
            ax.set_aspect("equal", adjustable="datalim")
            if covariances is not None and col == 1:
                _draw_ellipses(ax, poses[:, [a, b]], pos_cov[:, [a, b]][:, :, [a, b]],
                               max_ellipses)
                label = f"{label}, 2σ position ellipses"
            ax.set_title(f"{label} ({'xyz'[a]}–{'xyz'[b]})")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
