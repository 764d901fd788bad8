"""A solved calibration as text: the summary, the calibration TOML, and an optional PNG plot.

The TOML is a partial profile (only ``[geometry]``) that ``apply_calibration`` overlays, so
``run --calibration``, ``replay --calibration`` and ``config push`` accept it; the comments
carry the uncertainties and residuals.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from spiel_edge.calibrate.fit import Calibration
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


def calibration_toml(cal: Calibration, source: str = "", validation=None) -> str:
    header = ["# spiel-edge calibration" + (f" from {source}" if source else "")]
    header += ["# " + line for line in summary_lines(cal)]
    if validation is not None:
        header += ["# " + line for line in validation_lines(validation)]
    return "\n".join(header) + "\n" + dump_toml({"geometry": geometry_table(cal.geometry)})


def _mm(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f} mm"


def validation_lines(v) -> list[str]:
    """The before/after figures of :class:`spiel_edge.calibrate.validate.Validation`."""
    cv_b, cv_a = v.before, v.after
    lines = []
    if v.folds >= 2 and cv_b.acquisitions:
        lines += [
            f"on positions it did not fit ({v.positions} (x, y) positions in {v.folds} folds, "
            f"each solved from the others): median 3-D error {_mm(cv_b.median_mm)} before, "
            f"{_mm(cv_a.median_mm)} after (mean {_mm(cv_b.mean_mm)} -> "
            f"{_mm(cv_a.mean_mm)}; fixed {cv_b.fixes} -> {cv_a.fixes} of {cv_b.acquisitions})",
        ]
    else:
        lines.append(
            f"not cross-validated: {v.positions} (x, y) position(s); at least two are needed"
        )
    lines.append(
        f"on the acquisitions it was solved from (in-sample, flatters it): median "
        f"{_mm(v.in_sample_before.median_mm)} before, {_mm(v.in_sample_after.median_mm)} after "
        f"(mean {_mm(v.in_sample_before.mean_mm)} -> {_mm(v.in_sample_after.mean_mm)})"
    )
    lines += [f"fold not solved: {f}" for f in v.failed_folds]
    return lines


def report_text(cal: Calibration, v, source: str, output: str | None, refused: bool) -> str:
    """The short report a person reads: what it was solved from, what moved, whether it helps
    on unseen positions, and what was done about it."""
    lines = [f"calibration report: {cal.n_acquisitions} acquisitions from {source}"]
    moved = _largest_moves(cal)
    if moved:
        lines.append("largest changes: " + ", ".join(moved))
    lines += validation_lines(v)
    if v.worse:
        if refused:
            done = f"not written to {output} (--force writes it anyway)"
        elif output:
            done = f"written to {output} anyway (--force)"
        else:
            done = "nothing was to be written (no --output)"
        lines.append(
            f"verdict: WORSE on positions it did not fit; {done}. The start may already fit "
            "this board (the built-in profile was tuned on spiel-icra23), or the targets may "
            "not separate the parameters: --fix keeps some at the start's values"
        )
    elif v.folds < 2:
        lines.append("verdict: unchecked (one position); use it with care")
    else:
        lines.append("verdict: better on positions it did not fit")
    return "\n".join(lines) + "\n"


def _largest_moves(cal: Calibration, count: int = 3) -> list[str]:
    start = _values(cal.start)
    r = cal.result
    rows = []
    for name, value in zip(r.names, r.values, strict=True):
        unit = "samples" if name.startswith("d") else ("m/s" if name == "c" else "mm")
        if unit == "mm":
            rows.append((abs(value - start[name]), f"{name} {value - start[name]:+.1f} mm"))
    rows.sort(reverse=True)
    return [text for size, text in rows[:count] if size >= 0.5]


def plot_calibration(cal: Calibration, path: str | Path, validation=None) -> None:
    """PNG: top view of the start and calibrated geometry with targets, residuals per channel,
    and (with ``validation``) the 3-D error before and after on the held-out positions."""
    from spiel_edge.view import pyplot

    plt = pyplot()
    panels = 3 if validation is not None else 2
    fig, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 5))
    ax_geo, ax_res = axes[0], axes[1]
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
    if validation is not None:
        _plot_before_after(axes[2], validation)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_before_after(ax, v) -> None:
    before, after = v.before.errors_mm, v.after.errors_mm
    label = "held-out positions"
    if not before:  # one position: only the in-sample figures exist
        before, after = v.in_sample_before.errors_mm, v.in_sample_after.errors_mm
        label = "in-sample"
    top = max([*before, *after, 1.0])
    bins = np.linspace(0.0, top, 25)
    ax.hist(before, bins=bins, alpha=0.6, color="tab:blue", label=f"before ({_mm(_mean(before))})")
    ax.hist(after, bins=bins, alpha=0.6, color="tab:orange", label=f"after ({_mm(_mean(after))})")
    ax.set(xlabel="3-D error (mm)", ylabel="acquisitions", title=f"error, {label}")
    ax.legend(fontsize=8)


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


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
