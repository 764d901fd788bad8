"""Boards with three or more listening channels and I/Q samples (``signal = "iq"``): 3-D
positions with each matched echo timed by the carrier phase.

The pairs' magnitude is the envelope: preprocess, detect, MEMG fit, association and the echo
quality run on it as on an envelope board (pipeline/staged.py). Then, per target, each matched
echo's envelope ToA is refined by the carrier phase with the one-transducer code
(:func:`spiel_edge.pipeline.ranging.iq_refine`: the wrap nearest the envelope, the profile's
``[ranging]`` ``iq_phase_offset_rad``, ``iq_drift_samples`` and ``iq_wrap_margin``), and
weighted in the intersection and the covariance by its expected error ``[ranging] iq_sigma``
(:func:`~spiel_edge.pipeline.ranging.toa_sigma`). An echo whose wrap is not trusted keeps the
envelope's ToA and weight. A background in pairs is subtracted from the frame's pairs
(coherently: a static echo on a target's echo turns its phase and bends its magnitude, and the
difference of magnitudes removes neither); the envelope is then the difference's magnitude.

Each target says which timing it used (``timing``: "iq" every matched echo by the phase,
"mixed" some, "envelope" none), and so does the record (its best target's). Amplitudes in place
of pairs (a board that keeps the phase apart) are timed by the envelope. The staged path only:
the compiled kernels know no phase. docs/hardware-3d.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.pipeline.ranging import CONFIDENCE_COLUMN, iq_refine, toa_sigma
from spiel_edge.pipeline.staged import Pipeline, Result
from spiel_edge.profile.specs import Profile

log = logging.getLogger(__name__)


@dataclass
class IqResult(Result):
    """A Result whose record says how its best target's echoes were timed."""

    timing: str | None = None

    def record(self) -> dict:
        out = super().record()
        out["timing"] = self.timing
        return out


def baseband(pairs: np.ndarray) -> np.ndarray:
    """(channels, 2 x samples) (q, i) interleaved -> complex i + j q (channels, samples)."""
    z = np.empty((pairs.shape[0], pairs.shape[1] // 2), dtype=np.complex128)
    z.real, z.imag = pairs[:, 1::2], pairs[:, 0::2]  # no arithmetic: non-finite input stays quiet
    return z


class IqPipeline(Pipeline):
    """The 3-D pipeline of an I/Q profile; ``process`` takes (q, i) pairs or amplitudes."""

    takes_iq = True  # a live I/Q stream hands this pipeline its pairs (runtime/loop.py)

    def __init__(self, profile: Profile, associator=None, **kwargs):
        super().__init__(profile, associator, **kwargs)
        acq = profile.acquisition
        self.cycles_per_sample = acq.carrier_hz / acq.sample_rate_hz
        self.phase_on = profile.ranging.timing == "iq"
        self._baseband: np.ndarray | None = None  # the acquisition being processed
        wrap, error = 1.0 / self.cycles_per_sample, profile.ranging.envelope_sigma[0]
        if self.phase_on and wrap < 2.0 * error:  # e.g. 22 kHz at 175 kHz: 0.126 sample
            log.warning(
                "profile %r: the carrier phase wraps every %.3g samples, under twice the "
                "envelope's expected ToA error (%.3g, [ranging] envelope_sigma): it will often "
                "take a wrong wrap; [ranging] timing = 'envelope' is safer",
                profile.name,
                wrap,
                error,
            )

    def expected_shape(self) -> tuple[int, int]:
        return self.profile.geometry.n_channels, 2 * self.profile.acquisition.n_samples

    def check_shape(self, frames: np.ndarray, what: str = "frames") -> None:
        n_ch, n = self.profile.geometry.n_channels, self.profile.acquisition.n_samples
        if np.shape(frames) not in ((n_ch, n), (n_ch, 2 * n)):
            raise InputError(
                f"{what} has shape {np.shape(frames)}, profile {self.profile.name!r} expects "
                f"{(n_ch, 2 * n)} (q, i interleaved) or amplitudes {(n_ch, n)}"
            )

    def has_phase(self, frames: np.ndarray) -> bool:
        return np.shape(frames)[1] == 2 * self.profile.acquisition.n_samples

    def envelope(self, frames: np.ndarray) -> np.ndarray:
        f = np.asarray(frames, dtype=np.float64)
        return np.hypot(f[:, 0::2], f[:, 1::2]) if self.has_phase(f) else f

    def process(
        self, frames: np.ndarray, background: np.ndarray | None = None, *, timed: bool = False
    ) -> IqResult:
        self.check_shape(frames)
        if background is not None:
            self.check_shape(background, "background")
        raw = np.asarray(frames, dtype=np.float64)
        env, env_bg = self.envelope(raw), None if background is None else self.envelope(background)
        if self.has_phase(raw):
            z = baseband(raw)
            subtract = self.profile.preprocess.background_subtraction
            if subtract and background is not None and self.has_phase(background):
                # coherent: the static echoes leave exactly; the stages see a captured, empty
                # background (its scale and weights are a captured background's)
                z = z - baseband(np.asarray(background, dtype=np.float64))
                env, env_bg = np.abs(z), np.zeros_like(env)
            self._baseband = z if self.phase_on else None
        try:
            result = super().process(env, env_bg, timed=timed)
        finally:
            self._baseband = None
        values = {f.name: getattr(result, f.name) for f in fields(Result)}
        timing = result.targets[0].timing if result.targets else None
        return IqResult(**values, timing=timing)

    def phase_timing(self, feats, matched, use, picked, weights, shift) -> tuple:
        """Each matched echo's ToA refined by the carrier phase where its wrap is trusted:
        its ToA (the shift folded in), weight 1 / ``[ranging] iq_sigma``'s expected error."""
        z = self._baseband
        if z is None:
            return picked, weights, shift, "envelope"
        r = self.profile.ranging
        shift = np.broadcast_to(np.asarray(shift, dtype=np.float64), picked.shape).copy()
        picked, weights = picked.copy(), np.array(weights, dtype=np.float64)
        channels = np.flatnonzero(use)
        timed = 0
        for c in channels:
            t = iq_refine(
                picked[c] + shift[c],
                z[c].real,
                z[c].imag,
                self.cycles_per_sample,
                r.iq_phase_offset_rad,
                r.iq_drift_samples,
                r.iq_wrap_margin,
            )
            if t is None:
                continue
            alpha, confidence = feats[c, matched[c], 0], feats[c, matched[c], CONFIDENCE_COLUMN]
            range_mm = (t - self.delays[c]) * self.profile.mm_per_sample / 2.0
            picked[c], shift[c] = t, 0.0
            weights[c] = 1.0 / toa_sigma(r.iq_sigma, float(alpha), range_mm, float(confidence))
            timed += 1
        timing = "iq" if timed == len(channels) else "mixed" if timed else "envelope"
        return picked, weights, shift, timing

    def kernel_constants(self) -> dict | None:
        return None  # the carrier phase runs on the staged path only
