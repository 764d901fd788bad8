"""Boards with one or two listening transducers: a range per acquisition (one), or a range and
a bearing in the plane of the pair and the facing (two), each with its variance.

preprocess -> detect -> memg (the profile's window) -> features as for three or more channels,
then per listening channel the chosen echo (``[ranging] echo``), its time of arrival from the
envelope or, with I/Q samples, refined by the carrier phase (:func:`iq_refine`), and the
expected ToA error of that timing (:func:`toa_sigma`). One transducer: range = half the echo
path (pulse-echo); two: the point in their plane whose two echo paths match (Gauss-Newton,
two equations, two unknowns) and its covariance. docs/hardware-ranging.md.

I/Q frames are (channels, 2 x samples), q and i interleaved (the wire order of
``device/iq.py``); their envelope is the magnitude.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.pipeline.staged import Result, Target, front_stages, no_clock
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.pipeline.stages.static_scene import load_static_model
from spiel_edge.profile.specs import MAX_TARGETS_LIMIT, Profile

REASON_NO_ECHO = "no echo on a listening transducer"
REASON_RANGE_ONLY = "one transducer: a range, no direction"
REASON_NO_PAIR = "the two transducers' echoes do not fit one target"
CONFIDENCE_COLUMN = 4  # features: echo confidence
STAGES = ("preprocess", "detect", "memg", "features", "range")


@dataclass
class RangeResult(Result):
    """A Result with the range (mm, from the transducer that emits; half the echo path) and,
    for two transducers, the bearing (degrees from the facing, towards the second one)."""

    range_mm: float | None = None
    range_var_mm2: float | None = None
    bearing_deg: float | None = None
    bearing_var_deg2: float | None = None
    timing: str | None = None  # "envelope" or "iq": what timed the echo(es)
    n_listening: int = 1
    envelope_toa: list | None = None  # per chosen echo, the envelope ToA (samples; not recorded)

    def record(self) -> dict:
        out = super().record()
        out["range_mm"] = _round(self.range_mm, 3)
        out["range_var_mm2"] = _round(self.range_var_mm2, 5)
        if self.bearing_deg is not None or self.n_listening == 2:
            out["bearing_deg"] = _round(self.bearing_deg, 3)
            out["bearing_var_deg2"] = _round(self.bearing_var_deg2, 4)
        out["timing"] = self.timing
        return out


def _round(v: float | None, digits: int) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), digits)


class RangeAssociator:
    """Stands where the 3-D pipeline's associator is (commands print its name)."""

    name = "ranging"


class RangePipeline:
    """The pipeline of a one- or two-transducer profile; ``process`` as Pipeline's."""

    def __init__(self, profile: Profile, *, saturation: float = 65535.0):
        self.profile = profile
        g = profile.geometry
        self.listening = np.flatnonzero(g.listening_mask())
        if not 1 <= len(self.listening) <= 2:
            raise InputError(f"profile {profile.name!r}: ranging needs 1 or 2 listening channels")
        self.associator = RangeAssociator()
        self.echo_timing = None
        self.max_targets = 1
        self.saturation = saturation
        self.static_model = load_static_model(profile)
        self.iq = profile.acquisition.signal == "iq"
        self.takes_iq = self.iq  # a live I/Q stream hands this pipeline its (q, i) pairs
        self.delays = np.asarray(g.delays(), dtype=np.float64)
        self.channels_mm = np.asarray(g.channels_mm, dtype=np.float64)
        self.emitter_mm = np.asarray(g.emitter_mm, dtype=np.float64)
        self.facing = np.asarray(g.facing, dtype=np.float64)
        if len(self.listening) == 2:
            self.plane = pair_plane(self.channels_mm[self.listening], self.facing)

    def set_max_targets(self, k: int) -> None:
        if not (isinstance(k, int | np.integer) and 1 <= k <= MAX_TARGETS_LIMIT):
            raise InputError(
                f"max_targets must be an integer in [1, {MAX_TARGETS_LIMIT}], got {k!r}"
            )
        # one target per acquisition: a rangefinder reports its chosen echo

    def expected_shape(self) -> tuple[int, int]:
        n = self.profile.acquisition.n_samples
        return self.profile.geometry.n_channels, 2 * n if self.iq else n

    def check_shape(self, frames: np.ndarray, what: str = "frames") -> None:
        """An I/Q profile also takes amplitudes (channels, n): a board that sends its
        envelope (device/iq.py keeps the phase apart), timed by the envelope."""
        n_ch, n = self.profile.geometry.n_channels, self.profile.acquisition.n_samples
        if self.iq and np.shape(frames) == (n_ch, n):
            return
        if np.shape(frames) != self.expected_shape():
            kind = " (q, i interleaved)" if self.iq else ""
            raise InputError(
                f"{what} has shape {np.shape(frames)}, profile {self.profile.name!r} expects "
                f"{self.expected_shape()}{kind}"
            )

    def has_phase(self, frames: np.ndarray) -> bool:
        return self.iq and np.shape(frames)[1] == 2 * self.profile.acquisition.n_samples

    def envelope(self, frames: np.ndarray) -> np.ndarray:
        if not self.has_phase(frames):
            return np.asarray(frames, dtype=np.float64)
        f = np.asarray(frames, dtype=np.float64)
        return np.hypot(f[:, 0::2], f[:, 1::2])

    def process(
        self, frames: np.ndarray, background: np.ndarray | None = None, *, timed: bool = False
    ) -> RangeResult:
        p = self.profile
        self.check_shape(frames)
        if background is not None:  # amplitudes or pairs, either (its envelope is used)
            self.check_shape(background, "background")
        clock = time.perf_counter_ns if timed else no_clock
        t0 = clock()
        raw = np.asarray(frames, dtype=np.float64)
        if not p.preprocess.background_subtraction:
            background = None
        elif background is None:
            background = self.static_model
        bg = None if background is None else self.envelope(background)
        feats, counts, (t1, t2, t3, t4), y = front_stages(p, self.envelope(raw), bg, clock)
        result = self._range(raw, y, feats, counts)
        t5 = clock()
        if timed:
            stamps = (t0, t1, t2, t3, t4, t5)
            result.timings_us = {s: (stamps[i + 1] - stamps[i]) / 1e3 for i, s in enumerate(STAGES)}
            result.timings_us["end_to_end"] = (t5 - t0) / 1e3
        return result

    def _range(self, raw, y, feats, counts) -> RangeResult:
        toa = feats[:, :, TOA_COLUMN]
        echoes = [[float(v) for v in toa[c, : counts[c]]] for c in range(len(counts))]
        n_ch = len(counts)
        base = {"echoes": echoes, "features": feats, "counts": counts}
        empty = {"matched": [None] * n_ch, "n_listening": len(self.listening)}
        picks = self._pick(feats, counts)
        if picks is None:
            reason = REASON_NO_PAIR if len(self.listening) == 2 and (counts > 0).all() else None
            return RangeResult(None, reason or self._why_empty(raw, counts), None, **base, **empty)
        coarse = [self.envelope_toa(y, feats, c, k) for c, k in picks]
        timed = [self._time(raw, t, feats, c, k) for t, (c, k) in zip(coarse, picks, strict=True)]
        toas = np.array([t for t, _, _ in timed])
        sigmas = np.array([s for _, s, _ in timed])
        timing = "iq" if all(kind == "iq" for _, _, kind in timed) else "envelope"
        chans = np.array([c for c, _ in picks])
        mmps = self.profile.mm_per_sample * self.profile.ranging.range_scale
        paths = (toas - self.delays[chans]) * mmps
        path_sigmas = sigmas * mmps
        matched: list[int | None] = [None] * n_ch
        for c, k in picks:
            matched[c] = int(k)
        extra = {
            "matched": matched,
            "timing": timing,
            "n_listening": len(self.listening),
            "envelope_toa": coarse,
        }
        if len(picks) == 1:
            r, r_sigma = paths[0] / 2.0, path_sigmas[0] / 2.0
            return RangeResult(
                None, REASON_RANGE_ONLY, None, **base, range_mm=r, range_var_mm2=r_sigma**2, **extra
            )
        solved = solve_pair(
            paths, path_sigmas, self.channels_mm[chans], self.emitter_mm, self.plane,
            math.radians(self.profile.ranging.out_of_plane_std_deg),
        )  # fmt: skip
        if solved is None:
            return RangeResult(None, REASON_NO_PAIR, None, **base, **extra)
        pos, cov, bearing, bearing_var, r, r_var = solved
        target = Target(pos, cov, 0.0, matched, 0.0)
        return RangeResult(
            pos,
            None,
            0.0,
            **base,
            targets=[target],
            range_mm=r,
            range_var_mm2=r_var,
            bearing_deg=bearing,
            bearing_var_deg2=bearing_var,
            **extra,
        )

    def _pick(self, feats, counts) -> list[tuple[int, int]] | None:
        """(channel, echo index) per listening channel, or None when one has none fitting."""
        first = int(self.listening[0])
        k0 = self._choose(feats, counts, first)
        if k0 is None:
            return None
        if len(self.listening) == 1:
            return [(first, k0)]
        second = int(self.listening[1])
        mmps = self.profile.mm_per_sample * self.profile.ranging.range_scale
        baseline = float(np.linalg.norm(self.channels_mm[second] - self.channels_mm[first]))
        slack = baseline + self.profile.ranging.pair_tolerance_mm
        p0 = (feats[first, k0, TOA_COLUMN] - self.delays[first]) * mmps
        best = None
        for k in range(int(counts[second])):
            pk = (feats[second, k, TOA_COLUMN] - self.delays[second]) * mmps
            if abs(pk - p0) <= slack and (best is None or self._better(feats[second], k, best)):
                best = k
        return None if best is None else [(first, k0), (second, best)]

    def _better(self, f, k, other) -> bool:
        if self.profile.ranging.echo == "strongest":
            return f[k, 0] > f[other, 0]
        return f[k, TOA_COLUMN] < f[other, TOA_COLUMN]

    def _choose(self, feats, counts, c) -> int | None:
        n = int(counts[c])
        if n == 0:
            return None
        best = 0
        for k in range(1, n):
            if self._better(feats[c], k, best):
                best = k
        return best

    def envelope_toa(self, y, feats, c, k) -> float:
        """The envelope's ToA of echo k of channel c: the MEMG estimator's, averaged with the
        data's peak by ``[ranging] peak_weight``."""
        r = self.profile.ranging
        t = float(feats[c, k, TOA_COLUMN])
        if r.peak_weight > 0:
            m = self.profile.memg
            t_peak = data_peak(y[c], t, m.window_before + m.window_after)
            t = (1.0 - r.peak_weight) * t + r.peak_weight * t_peak
        return t

    def _time(self, raw, t_env, feats, c, k) -> tuple[float, float, str]:
        """The echo's ToA (samples) from its envelope ToA, its expected error (samples) and
        which timing gave it."""
        r = self.profile.ranging
        alpha = float(feats[c, k, 0])
        confidence = float(feats[c, k, CONFIDENCE_COLUMN])
        scale = self.profile.mm_per_sample * r.range_scale
        range_mm = (t_env - self.delays[c]) * scale / 2.0
        if r.timing == "iq" and self.has_phase(raw):
            acq = self.profile.acquisition
            q, i = raw[c, 0::2], raw[c, 1::2]
            t_iq = iq_refine(
                t_env,
                i,
                q,
                acq.carrier_hz / acq.sample_rate_hz,
                r.iq_phase_offset_rad,
                r.iq_drift_samples,
                r.iq_wrap_margin,
            )
            if t_iq is not None:
                return t_iq, toa_sigma(r.iq_sigma, alpha, range_mm, confidence), "iq"
        return t_env, toa_sigma(r.envelope_sigma, alpha, range_mm, confidence), "envelope"

    def _why_empty(self, raw, counts) -> str:
        if raw.size and np.mean(np.abs(raw) >= self.saturation) > 0.5:
            return "frame is saturated"
        if raw.size and np.ptp(raw) == 0:
            return "frame is flat (all samples equal): no signal"
        return REASON_NO_ECHO


def toa_sigma(model, alpha: float, range_mm: float, confidence: float) -> float:
    """The expected ToA error (samples) of one echo by the profile's error model
    ``[a, b, c, d]``: sqrt(a^2 + (b / alpha)^2 + (c range / 100)^2 + (d (1 - confidence))^2)."""
    a, b, c, d = model
    alpha = alpha if alpha > 0 and math.isfinite(alpha) else 1e-9
    confidence = confidence if math.isfinite(confidence) else 0.0
    miss = min(max(1.0 - confidence, 0.0), 1.0)
    return math.sqrt(a * a + (b / alpha) ** 2 + (c * range_mm / 100.0) ** 2 + (d * miss) ** 2)


def data_peak(y: np.ndarray, t: float, span: int) -> float:
    """The sub-sample maximum of the envelope y (parabola through the largest sample and its
    neighbours) within ``span`` samples after floor(t): the echo's peak, found from its
    fitted ToA (which may sit on its rising edge)."""
    lo = max(int(math.floor(t)), 0)
    hi = min(lo + span + 1, len(y))
    if hi - lo < 1:
        return t
    k = lo + int(np.argmax(y[lo:hi]))
    if k <= 0 or k >= len(y) - 1:
        return float(k)
    den = y[k - 1] - 2.0 * y[k] + y[k + 1]
    return float(k) if den >= 0.0 else k + 0.5 * (y[k - 1] - y[k + 1]) / den


def echo_phase(t: float, i: np.ndarray, q: np.ndarray) -> float | None:
    """The carrier phase (radians) of the echo at ToA ``t`` (samples): the argument of the I/Q
    pairs summed over the two samples around t, each weighted by its nearness (linear
    interpolation of the complex baseband, which keeps the phase where the magnitude is
    large). None outside the frame."""
    n = len(i)
    lo = int(math.floor(t))
    if lo < 0 or lo + 1 >= n:
        return None
    w = t - lo
    re = (1.0 - w) * i[lo] + w * i[lo + 1]
    im = (1.0 - w) * q[lo] + w * q[lo + 1]
    if re == 0.0 and im == 0.0:
        return None
    return math.atan2(im, re)


def iq_refine(
    t_env: float,
    i: np.ndarray,
    q: np.ndarray,
    cycles_per_sample: float,
    offset_rad: float,
    drift: tuple,
    margin: float,
) -> float | None:
    """The envelope ToA ``t_env`` refined by the carrier phase, or None (wrap not trusted).

    A delay of t samples turns the baseband phase by -2 pi f t (f = carrier / sample rate),
    so the phase gives the ToA modulo one wrap w = 1 / f (half a sample at fs = carrier / 2):
    t_phase = (offset - phase) / (2 pi f) + k w, offset fitted so that t_phase is on the
    envelope's scale (the same delay). The envelope says which wrap k: the one nearest
    ref = t_env - (a + b t_env), where drift = (a, b) is the envelope-to-phase offset fitted
    over range (it drifts by ~0.2 sample over 137-227 mm on the DK-CH101). When t_phase's
    nearest wrap is within ``margin`` x w of the boundary between two wraps, both are nearly
    as likely: None (the caller keeps the envelope timing)."""
    phase = echo_phase(t_env, i, q)
    if phase is None:
        return None
    wrap = 1.0 / cycles_per_sample
    ref = t_env - (drift[0] + drift[1] * t_env)
    t_phase = (offset_rad - phase) / (2.0 * math.pi * cycles_per_sample)
    step = math.remainder(t_phase - ref, wrap)  # in [-w/2, w/2]
    if abs(step) > wrap * (0.5 - margin):
        return None
    return ref + step


def pair_plane(points: np.ndarray, facing: np.ndarray) -> tuple[np.ndarray, ...]:
    """(origin, u, w, v): midpoint of the pair, unit baseline u (first -> second), unit w
    along the facing's part across the baseline (the bearing's zero), and v = u x w (the
    direction the pair cannot see)."""
    origin = (points[0] + points[1]) / 2.0
    u = (points[1] - points[0]) / np.linalg.norm(points[1] - points[0])
    w = facing - (facing @ u) * u
    w = w / np.linalg.norm(w)
    return origin, u, w, np.cross(u, w)


def solve_pair(paths, sigmas, receivers, emitter, plane, out_of_plane_rad):
    """The point P = origin + x u + z w (z > 0) whose echo paths |P - emitter| + |P - R_i|
    equal ``paths``; (position, 3x3 covariance, bearing deg, its variance, range mm, its
    variance) or None when no such point is found."""
    origin, u, w, v = plane
    r0 = paths[0] / 2.0
    x, z = 0.0, max(r0, 1.0)
    for _ in range(30):
        pos = origin + x * u + z * w
        f, jac = np.empty(2), np.empty((2, 2))
        de = pos - emitter
        ne = np.linalg.norm(de)
        for j in range(2):
            dr = pos - receivers[j]
            nr = np.linalg.norm(dr)
            if ne == 0 or nr == 0:
                return None
            g = de / ne + dr / nr
            f[j] = ne + nr - paths[j]
            jac[j] = (g @ u, g @ w)
        try:
            step = np.linalg.solve(jac, -f)
        except np.linalg.LinAlgError:
            return None
        x, z = x + step[0], z + step[1]
        if abs(step).max() < 1e-7:
            break
    pos = origin + x * u + z * w
    if (
        z <= 0
        or not np.all(np.isfinite(pos))
        or abs(np.linalg.norm(pos - emitter) + np.linalg.norm(pos - receivers[0]) - paths[0]) > 1e-3
    ):
        return None
    try:
        inv = np.linalg.inv(jac)
    except np.linalg.LinAlgError:
        return None
    cov2 = inv @ np.diag(np.asarray(sigmas) ** 2) @ inv.T  # (x, z)
    basis = np.stack([u, w], axis=1)  # 3 x 2
    rng = math.hypot(x, z)
    cov = basis @ cov2 @ basis.T + np.outer(v, v) * (rng * out_of_plane_rad) ** 2
    bearing = math.degrees(math.atan2(x, z))
    grad_b = np.array([z, -x]) / (rng * rng)  # d atan2(x, z) / d(x, z)
    bearing_var = math.degrees(1.0) ** 2 * float(grad_b @ cov2 @ grad_b)
    de = pos - emitter
    r = float(np.linalg.norm(de))
    grad_r = np.array([de @ u, de @ w]) / r
    r_var = float(grad_r @ cov2 @ grad_r)
    return pos, cov, bearing, bearing_var, r, r_var
