"""Evaluation error by position: one panel per height, each labelled position a disc coloured
by its mean 3-D error (grey: never fixed), the figure `evaluate --plot` writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from spiel_edge.view import pyplot

SIZE_IN_PER_PANEL, DPI = 4.5, 100


def draw_error_by_position(errors: dict[tuple, list[float]], path: str | Path) -> dict:
    """``errors``: (x, y, z) -> the 3-D errors of its fixed acquisitions ([] when none)."""
    plt = pyplot()
    heights = sorted({k[2] for k in errors})
    n = max(len(heights), 1)
    fig, axes = plt.subplots(1, n, figsize=(SIZE_IN_PER_PANEL * n + 1.0, 4.5), squeeze=False)
    means = [float(np.mean(v)) for v in errors.values() if v]
    top = max(means + [1.0])
    drawn = 0
    scatter = None
    for ax, z in zip(axes[0], heights, strict=False):
        keys = [k for k in errors if k[2] == z]
        fixed = [k for k in keys if errors[k]]
        lost = [k for k in keys if not errors[k]]
        if fixed:
            scatter = ax.scatter(
                [k[0] for k in fixed],
                [k[1] for k in fixed],
                c=[np.mean(errors[k]) for k in fixed],
                s=120,
                cmap="viridis",
                vmin=0.0,
                vmax=top,
            )
        if lost:
            ax.scatter([k[0] for k in lost], [k[1] for k in lost], s=120, c="0.7", marker="s")
        drawn += len(keys)
        ax.set(xlabel="x (mm)", title=f"z = {z:g} mm", aspect="equal")
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("y (mm)")
    if scatter is not None:
        fig.colorbar(scatter, ax=list(axes[0]), label="mean 3-D error (mm)")
    fig.suptitle("evaluation: error by position (grey squares: never fixed)")
    fig.canvas.draw()
    size = fig.canvas.get_width_height()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return {"positions": drawn, "heights": len(heights), "size": size}
