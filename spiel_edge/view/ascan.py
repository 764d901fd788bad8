"""A-scans: each channel's envelope (after background subtraction), the detected echoes, the
fitted MEMG components and their sum, and the echo the association matched."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from spiel_edge.view import pyplot

ECHO_COLOUR = "#ff0000"  # pure red: the tests find the echo marks by it
MATCH_COLOUR = "#00a000"
SIZE_IN, DPI = (10.0, 7.0), 100


def emg_curve(t: np.ndarray, alpha: float, mu: float, sigma: float, eta: float) -> np.ndarray:
    """One MEMG component (stages/memg.py's emg_value) over the times ``t``."""
    u = (t - mu) / sigma
    erf = np.array([math.erf(v) for v in eta * u / math.sqrt(2.0)])
    return alpha * np.exp(-0.5 * u * u) * (1.0 + erf)


def envelope_of(pipeline, frames: np.ndarray, background: np.ndarray | None) -> np.ndarray:
    """The envelope the pipeline fits: preprocessed as its first stage does."""
    from spiel_edge.pipeline.stages.preprocess import preprocess

    p = pipeline.profile
    if not p.preprocess.background_subtraction:
        background = None
    elif background is None:
        background = pipeline.static_model
    acq = p.acquisition
    return preprocess(
        frames,
        background,
        blind_zone=p.preprocess.blind_zone_samples,
        rf=acq.signal == "rf",
        carrier_cycles_per_sample=acq.carrier_hz / acq.sample_rate_hz,
    )


def draw_ascan(pipeline, frames, background, path: str | Path, title: str = "") -> dict:
    """Write the PNG; returns where the echo marks are, in pixels from the image's left edge,
    per channel (``marks``), with the image's ``size`` (width, height) in pixels."""
    plt = pyplot()
    result = pipeline.process(np.asarray(frames, np.float64), background)
    y = envelope_of(pipeline, np.asarray(frames, np.float64), background)
    n_ch, n_t = y.shape
    fig, axes = plt.subplots(n_ch, 1, figsize=SIZE_IN, sharex=True, squeeze=False)
    t_fine = np.linspace(0.0, n_t - 1, 8 * n_t)
    lines = []
    for ch in range(n_ch):
        ax = axes[ch, 0]
        ax.plot(np.arange(n_t), y[ch], color="0.2", lw=1.2, label="envelope")
        total = np.zeros_like(t_fine)
        echoes = result.echoes[ch]
        for k in range(len(echoes)):
            alpha, mu, sigma, eta = result.features[ch, k, :4]
            if np.isfinite([alpha, mu, sigma, eta]).all() and sigma > 0:
                curve = emg_curve(t_fine, alpha, mu, sigma, eta)
                total += curve
                ax.plot(t_fine, curve, color="tab:blue", lw=0.8, alpha=0.7)
        if len(echoes):
            ax.plot(t_fine, total, color="tab:blue", lw=1.0, ls="--", label="MEMG fit")
        for k, toa in enumerate(echoes):
            matched = result.matched[ch] == k
            ax.axvline(toa, color=MATCH_COLOUR if matched else ECHO_COLOUR, lw=1.5)
        ax.set_ylabel(f"ch {ch}")
        lines.append(echoes)
    axes[-1, 0].set_xlabel("sample (echo marks: red; the matched echo: green)")
    where = (
        ""
        if result.position_mm is None
        else " -> " + ", ".join(f"{v:.0f}" for v in result.position_mm) + " mm"
    )
    fig.suptitle((title or "A-scans") + where)
    axes[0, 0].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.canvas.draw()
    width, height = fig.canvas.get_width_height()
    marks = []
    for ch in range(n_ch):
        ax = axes[ch, 0]
        marks.append(
            [
                (float(ax.transData.transform((toa, 0.0))[0]), result.matched[ch] == k)
                for k, toa in enumerate(lines[ch])
            ]
        )
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return {"marks": marks, "size": (width, height), "echoes": lines}
