"""A solved calibration as text: the summary, the calibration TOML, and an optional PNG plot.

The TOML is a partial profile (only ``[geometry]``) that ``apply_calibration`` overlays, so
``run --calibration``, ``replay --calibration`` and ``config push`` accept it; the comments
carry the uncertainties and residuals.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from spiel_edge.calibrate.fit import Calibration
from spiel_edge.errors import SpielError
from spiel_edge.profile.schema import Geometry, dump_toml


def geometry_table(g: Geometry) -> dict:
    """The calibrated geometry as a TOML-ready ``[geometry]`` table (rounded below noise)."""
    return {
        "speed_of_sound_m_s": round(float(g.speed_of_sound_m_s), 3),
        "emitter_mm": [round(float(v), 3) for v in g.emitter_mm],
        "channels_mm": [[round(float(v), 3) for v in row] for row in g.channels_mm],
        "delay_samples": [round(float(v), 4) for v in g.delays()],
    }


def summary_lines(cal: Calibration) -> list[str]:
    """Human-readable: counts, robust scale, each parameter with its 1-sigma, per-channel residuals."""
    r = cal.result
    mm = cal.start.speed_of_sound_m_s * 1000.0 / cal.sample_rate_hz
    fixed = sorted(set(_all_names(cal)) - set(r.names))
    lines = [
        f"{cal.n_acquisitions} acquisitions: target echo found on {len(cal.observations)} of {cal.expected} "
        f"channels, {int(r.rejected.sum())} rejected as outliers; robust residual scale {r.scale:.3f} samples ({r.scale * mm:.1f} mm of path); "
        f"{cal.rounds} pick/solve rounds, {r.iterations} LM iterations{'' if r.converged else ' (NOT converged)'}",
        "parameter      start   calibrated   +-1 sigma",
    ]
    start = _values(cal.start)
    for name, value, std in zip(r.names, r.values, r.std, strict=True):
        unit = "samples" if name.startswith("d") else ("m/s" if name == "c" else "mm")
        lines.append(f"  {name:<8} {start[name]:>9.3f} {value:>11.3f}   {std:.3f} {unit}")
    if fixed:
        lines.append("fixed: " + ", ".join(fixed))
    lines.append("residuals per channel (samples): channel used rejected rms median")
    for row in cal.per_channel():
        lines.append(
            f"  {row['channel']:>2} {row['used']:>6} {row['rejected']:>5} {row['rms']:>8.3f} {row['median']:>8.3f}"
        )
    return lines


def calibration_toml(cal: Calibration, source: str = "") -> str:
    header = ["# spiel-edge calibration" + (f" from {source}" if source else "")]
    header += ["# " + line for line in summary_lines(cal)]
    return "\n".join(header) + "\n" + dump_toml({"geometry": geometry_table(cal.geometry)})


def write_calibration(cal: Calibration, path: str | Path, source: str = "") -> None:
    Path(path).write_text(calibration_toml(cal, source))


def plot_calibration(cal: Calibration, path: str | Path) -> None:
    """PNG: top view of the start and calibrated geometry with targets, and residuals per channel."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise SpielError(
            "the calibration plot needs matplotlib: pip install 'spiel-edge[plot]'"
        ) from exc
    fig, (ax_geo, ax_res) = plt.subplots(1, 2, figsize=(11, 5))
    targets = np.unique(cal.observations.targets_mm, axis=0)
    ax_geo.scatter(targets[:, 0], targets[:, 1], s=8, c="0.7", label="targets")
    for g, style, label in ((cal.start, "o", "start"), (cal.geometry, "x", "calibrated")):
        ax_geo.scatter(
            g.channels_mm[:, 0],
            g.channels_mm[:, 1],
            marker=style,
            s=60,
            label=f"receivers ({label})",
        )
        ax_geo.scatter([g.emitter_mm[0]], [g.emitter_mm[1]], marker=style, s=90, c="k")
    for n, (x, y, _z) in enumerate(cal.geometry.channels_mm):
        ax_geo.annotate(str(n), (x, y), textcoords="offset points", xytext=(6, 6))
    ax_geo.set(xlabel="x (mm)", ylabel="y (mm)", title="geometry (top view)", aspect="equal")
    ax_geo.legend(fontsize=8)
    ch, res, rej = cal.observations.channels, cal.result.residuals, cal.result.rejected
    n_ch = cal.start.n_channels
    ax_res.boxplot(
        [res[(ch == n) & ~rej] for n in range(n_ch)], tick_labels=[str(n) for n in range(n_ch)]
    )
    for n in range(n_ch):
        out = res[(ch == n) & rej]
        ax_res.scatter(np.full(out.size, n + 1), out, marker="x", c="r", s=12)
    ax_res.axhline(0.0, c="0.5", lw=0.8)
    ax_res.set(xlabel="channel", ylabel="residual (samples)", title="residuals (x = rejected)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _values(g: Geometry) -> dict[str, float]:
    out = {
        f"r{n}.{a}": float(g.channels_mm[n, i])
        for n in range(g.n_channels)
        for i, a in enumerate("xyz")
    }
    out.update({f"e.{a}": float(g.emitter_mm[i]) for i, a in enumerate("xyz")})
    out.update({f"d{n}": float(v) for n, v in enumerate(g.delays())})
    out["c"] = float(g.speed_of_sound_m_s)
    return out


def _all_names(cal: Calibration) -> list[str]:
    tied = np.linalg.norm(cal.start.channels_mm - cal.start.emitter_mm, axis=1) < 1.0
    names = [
        k for k in _values(cal.start) if not (k.startswith("r") and tied[int(k[1:].split(".")[0])])
    ]
    return names
