"""Optional plotting helpers (need the ``plot`` extra: matplotlib)."""

from __future__ import annotations

from typing import Any

import numpy as np


def plot_pose_graphs(path: str, kind: str, before: np.ndarray, after: np.ndarray,
                     edges: np.ndarray | None = None, title: str = "") -> None:
    """Save a before/after plot of pose positions (x–y; 3D graphs also x–z) to ``path``."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(
            "plotting needs matplotlib: pip install 'jaxpose[plot]'"
        ) from err
    views = [(0, 1)] if kind == "SE2" else [(0, 1), (0, 2)]
    fig, axes = plt.subplots(len(views), 2, figsize=(10, 4.5 * len(views)), squeeze=False)
    for row, (a, b) in enumerate(views):
        for col, (label, poses) in enumerate((("initial", before), ("optimised", after))):
            ax: Any = axes[row][col]
            if edges is not None and len(edges) <= 20000:
                seg = np.stack([poses[edges[:, 0]][:, [a, b]], poses[edges[:, 1]][:, [a, b]]], 1)
                from matplotlib.collections import LineCollection

                ax.add_collection(LineCollection(seg, linewidths=0.2, colors="0.7"))
            ax.plot(poses[:, a], poses[:, b], lw=0.6)
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_title(f"{label} ({'xyz'[a]}–{'xyz'[b]})")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
