"""Positions and tracks from records (run, replay, fuse): a top view (x, y) and a side view
(x, z), each target with its 95 % ellipse, tracks as lines, the ground truth where known."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.safety.limits import read_text_bounded
from spiel_edge.view import pyplot

CHI2_95_2DOF = 5.991
MAX_ELLIPSES = 200  # the last ones: a long run stays readable
MAX_RECORDS_BYTES = 256 << 20
SIZE_IN, DPI = (12.0, 5.5), 100


def read_records(path: str | Path) -> list[dict]:
    """NDJSON records; InputError naming the line when one is not a JSON object."""
    text = read_text_bounded(Path(path), MAX_RECORDS_BYTES, InputError, str(path), "records")
    records = []
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except ValueError:
            raise InputError(f"{path}:{n}: not a JSON record (NDJSON from run or replay)") from None
        if not isinstance(record, dict):
            raise InputError(f"{path}:{n}: not a JSON object")
        records.append(record)
    if not records:
        raise InputError(f"{path}: no records")
    return records


def _targets(record: dict) -> list[tuple[np.ndarray, np.ndarray | None]]:
    out = []
    for t in record.get("targets") or []:
        try:
            p = np.array(t["position_mm"], dtype=np.float64).reshape(3)
            c = t.get("covariance_mm2")
            c = None if c is None else np.array(c, dtype=np.float64).reshape(3, 3)
        except (KeyError, TypeError, ValueError):
            continue
        if np.isfinite(p).all():
            out.append((p, c))
    return out


def _ellipse(ax, centre, cov2, colour):
    from matplotlib.patches import Ellipse

    vals, vecs = np.linalg.eigh(cov2)
    if not (np.isfinite(vals).all() and vals.min() > 0):
        return
    w, h = 2.0 * np.sqrt(CHI2_95_2DOF * vals)
    angle = float(np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1])))
    ax.add_patch(Ellipse(centre, h, w, angle=angle, fill=False, color=colour, lw=0.6, alpha=0.5))


def draw_positions(records: list[dict], path: str | Path, title: str = "") -> dict:
    """Write the PNG; returns counts of what was drawn and the image size in pixels."""
    plt = pyplot()
    fig, (top, side) = plt.subplots(1, 2, figsize=SIZE_IN)
    points, truths, tracks = [], [], {}
    ellipses = 0
    for i, record in enumerate(records):
        late = i >= len(records) - MAX_ELLIPSES
        for p, c in _targets(record):
            points.append(p)
            if late and c is not None:
                _ellipse(top, p[[0, 1]], c[np.ix_([0, 1], [0, 1])], "tab:blue")
                _ellipse(side, p[[0, 2]], c[np.ix_([0, 2], [0, 2])], "tab:blue")
                ellipses += 1
        for tr in record.get("tracks") or []:
            try:
                tracks.setdefault(tr["track_id"], []).append(np.array(tr["position_mm"], float))
            except (KeyError, TypeError, ValueError):
                continue
        truth = record.get("truth_targets_mm") or [record.get("truth_mm")]
        for t in truth if isinstance(truth, list) else []:
            if isinstance(t, list) and len(t) == 3:
                truths.append(np.array(t, float))
    pts = np.array(points).reshape(-1, 3)
    for ax, (a, b), name in ((top, (0, 1), "top view"), (side, (0, 2), "side view")):
        ax.scatter(pts[:, a], pts[:, b], s=6, c="tab:blue", label=f"targets ({len(pts)})")
        for tid, path_ in tracks.items():
            xs = np.array(path_)
            ax.plot(xs[:, a], xs[:, b], lw=1.2, label=f"track {tid}" if len(tracks) <= 8 else None)
        if truths:
            tr = np.array(truths)
            ax.scatter(tr[:, a], tr[:, b], marker="x", s=30, c="k", label="truth")
        ax.scatter([0], [0], marker="^", s=80, c="tab:red", label="board")
        ax.set(xlabel="x (mm)", ylabel="yz"[b - 1] + " (mm)", title=name, aspect="equal")
        ax.grid(alpha=0.3)
    top.legend(fontsize=7, loc="best")
    fig.suptitle(title or f"{len(records)} records: targets with their 95 % ellipses")
    fig.tight_layout()
    fig.canvas.draw()
    size = fig.canvas.get_width_height()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return {"targets": len(pts), "ellipses": ellipses, "tracks": len(tracks), "size": size}
