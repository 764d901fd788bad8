"""The calibration solver: array geometry, delays and speed of sound from echo times.

Observation i: a target at a known position p_i, a channel n_i and its measured echo time
t_i (samples). The model is the pipeline's own (``pipeline/stages/locate.py``)::

    t = (|p - e| + |p - r_n|) * fs / (1000 c) + d_n

with emitter e, receiver r_n (mm), per-channel delay d_n (samples) and speed of sound c (m/s).
A channel within 1 mm of the emitter is monostatic and moves with it.

Gauge: the target positions fix the frame, so nothing is free up to a transformation. The
emitter's position is the array's offset from the frame the targets are given in (the
robot-to-board registration plus the acoustic centre's depth); when it is estimated, the
channels that are not free move rigidly with it. ``fix`` holds any of FIXABLE to keep
those parameters at their start values (e.g. ``receivers_z`` for a flat PCB when the targets
span too small a range of angles to separate a receiver's height from its delay).

Robust: Levenberg-Marquardt (analytic Jacobian, Marquardt scaling) inside iteratively
re-weighted least squares with Huber weights on the robust (MAD) residual scale; residuals
beyond ``reject_sigma`` scales get weight 0 and count as rejected echoes. Uncertainties come
from (J^T W J)^-1 at the solution scaled by the weighted residual variance.
Pure numpy: no I/O, no scipy.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.profile.schema import Geometry

log = logging.getLogger(__name__)

FIXABLE = ("emitter", "receivers", "receivers_z", "delays", "speed")
DEFAULT_FIX: frozenset[str] = frozenset()
MONOSTATIC_MM = 1.0
HUBER_K = 1.345  # 95% efficiency on Gaussian residuals
MIN_SCALE = 1e-3  # samples: floor of the robust scale (noise-free synthetic data)
_AXES = "xyz"


@dataclass(frozen=True)
class Observations:
    """Flat echo-time observations: targets (N, 3) mm, channels (N,) int, toa (N,) samples."""

    targets_mm: np.ndarray
    channels: np.ndarray
    toa: np.ndarray

    def __len__(self) -> int:
        return int(self.toa.shape[0])


@dataclass(frozen=True)
class CalibrationResult:
    geometry: Geometry
    names: list[str]  # estimated parameters, e.g. "r1.x", "d0", "c"
    values: np.ndarray
    std: np.ndarray  # 1-sigma uncertainty per estimated parameter
    residuals: np.ndarray  # (N,) samples, model - measured, at the solution
    weights: np.ndarray  # (N,) final robust weights; 0 = rejected
    scale: float  # robust residual scale (samples)
    iterations: int
    converged: bool

    @property
    def rejected(self) -> np.ndarray:
        return self.weights == 0

    def per_channel(self, channels: np.ndarray, n_channels: int) -> list[dict]:
        """Per channel: observations used, rejected, rms and median residual (samples)."""
        out = []
        for n in range(n_channels):
            sel = channels == n
            used = sel & ~self.rejected
            r = self.residuals[used]
            out.append(
                {
                    "channel": n,
                    "used": int(used.sum()),
                    "rejected": int((sel & self.rejected).sum()),
                    "rms": float(np.sqrt(np.mean(r**2))) if r.size else float("nan"),
                    "median": float(np.median(r)) if r.size else float("nan"),
                }
            )
        return out


@dataclass(frozen=True)
class _Layout:
    """Which geometry entries are free, and where they sit in the parameter vector."""

    receiver_idx: list[tuple[int, int]]  # (channel, axis)
    emitter_axes: list[int]
    delay_channels: list[int]
    speed: bool

    @property
    def size(self) -> int:
        return (
            len(self.receiver_idx)
            + len(self.emitter_axes)
            + len(self.delay_channels)
            + int(self.speed)
        )

    def names(self) -> list[str]:
        return (
            [f"r{n}.{_AXES[a]}" for n, a in self.receiver_idx]
            + [f"e.{_AXES[a]}" for a in self.emitter_axes]
            + [f"d{n}" for n in self.delay_channels]
            + (["c"] if self.speed else [])
        )


def solve(
    obs: Observations,
    start: Geometry,
    sample_rate_hz: float,
    *,
    fix: frozenset[str] | set[str] = DEFAULT_FIX,
    reject_sigma: float = 4.0,
    max_iterations: int = 100,
) -> CalibrationResult:
    """Robustly fit the free geometry parameters to ``obs`` starting from ``start``."""
    unknown = set(fix) - set(FIXABLE)
    if unknown:
        raise InputError(f"cannot fix {sorted(unknown)}; fixable: {', '.join(FIXABLE)}")
    _check_observations(obs, start.n_channels)
    tied = np.linalg.norm(start.channels_mm - start.emitter_mm, axis=1) < MONOSTATIC_MM
    layout = _layout(start, tied, np.unique(obs.channels), frozenset(fix))
    if layout.size == 0:
        raise InputError("everything is fixed: nothing to calibrate")
    if len(obs) <= layout.size:
        raise InputError(
            f"{len(obs)} echo times cannot determine {layout.size} parameters; capture more positions"
        )
    theta = _pack(start, layout)
    weights = np.ones(len(obs))
    scale, iterations, converged = 1.0, 0, False
    for _round in range(8):
        theta, its, converged = _lm(
            obs, start, tied, layout, sample_rate_hz, theta, weights, max_iterations
        )
        iterations += its
        r = _residuals(obs, _unpack(start, tied, layout, theta), sample_rate_hz)
        scale = _robust_scale(r, weights > 0)
        new = _huber_weights(r, scale, reject_sigma)
        if np.array_equal(new > 0, weights > 0) and np.allclose(new, weights, atol=1e-3):
            break
        weights = new
    geometry = _unpack(start, tied, layout, theta)
    r = _residuals(obs, geometry, sample_rate_hz)
    std = _uncertainty(obs, geometry, tied, layout, sample_rate_hz, r, weights)
    log.info(
        "calibration: %d echoes, %d rejected, scale %.3f samples, %d LM iterations",
        len(obs),
        int((weights == 0).sum()),
        scale,
        iterations,
    )
    return CalibrationResult(
        geometry, layout.names(), theta, std, r, weights, scale, iterations, converged
    )


def predict_toa(
    geometry: Geometry, targets_mm: np.ndarray, channels: np.ndarray, sample_rate_hz: float
) -> np.ndarray:
    """Echo time (samples) of each (target, channel) pair under ``geometry``."""
    k = sample_rate_hz / (1000.0 * geometry.speed_of_sound_m_s)
    le = np.linalg.norm(targets_mm - geometry.emitter_mm, axis=1)
    lr = np.linalg.norm(targets_mm - geometry.channels_mm[channels], axis=1)
    return (le + lr) * k + geometry.delays()[channels]


def _residuals(obs: Observations, g: Geometry, fs: float) -> np.ndarray:
    return predict_toa(g, obs.targets_mm, obs.channels, fs) - obs.toa


def _check_observations(obs: Observations, n_channels: int) -> None:
    n = len(obs)
    if obs.targets_mm.shape != (n, 3) or obs.channels.shape != (n,):
        raise InputError("observations need targets_mm (N, 3), channels (N,) and toa (N,)")
    if not (np.all(np.isfinite(obs.targets_mm)) and np.all(np.isfinite(obs.toa))):
        raise InputError("observations must be finite (drop missing echoes first)")
    if n and (obs.channels.min() < 0 or obs.channels.max() >= n_channels):
        raise InputError(f"observation channels must be in [0, {n_channels})")


def _layout(
    start: Geometry, tied: np.ndarray, observed: np.ndarray, fix: frozenset[str]
) -> _Layout:
    axes = [0, 1] if "receivers_z" in fix else [0, 1, 2]
    receivers = (
        [] if "receivers" in fix else [(int(n), a) for n in observed if not tied[n] for a in axes]
    )
    emitter = [] if "emitter" in fix else [0, 1, 2]
    delays = [] if "delays" in fix else [int(n) for n in observed]
    return _Layout(receivers, emitter, delays, "speed" not in fix)


def _pack(g: Geometry, layout: _Layout) -> np.ndarray:
    parts = [g.channels_mm[n, a] for n, a in layout.receiver_idx]
    parts += [g.emitter_mm[a] for a in layout.emitter_axes]
    parts += [g.delays()[n] for n in layout.delay_channels]
    parts += [g.speed_of_sound_m_s] if layout.speed else []
    return np.array(parts, dtype=np.float64)


def _unpack(start: Geometry, tied: np.ndarray, layout: _Layout, theta: np.ndarray) -> Geometry:
    emitter = start.emitter_mm.copy()
    delays = start.delays().astype(np.float64).copy()
    i = len(layout.receiver_idx)
    for a in layout.emitter_axes:
        emitter[a] = theta[i]
        i += 1
    # the array moves rigidly with the emitter; free receiver coordinates are then overwritten
    channels = start.channels_mm + (emitter - start.emitter_mm)
    for j, (n, a) in enumerate(layout.receiver_idx):
        channels[n, a] = theta[j]
    for n in layout.delay_channels:
        delays[n] = theta[i]
        i += 1
    speed = float(theta[i]) if layout.speed else start.speed_of_sound_m_s
    return dataclasses.replace(
        start,
        channels_mm=channels,
        emitter_mm=emitter,
        delay_samples=delays,
        speed_of_sound_m_s=speed,
    )


def _jacobian(
    obs: Observations, g: Geometry, tied: np.ndarray, layout: _Layout, fs: float
) -> np.ndarray:
    p, ch = obs.targets_mm, obs.channels
    k = fs / (1000.0 * g.speed_of_sound_m_s)
    ue = p - g.emitter_mm
    ur = p - g.channels_mm[ch]
    le = np.maximum(np.linalg.norm(ue, axis=1), 1e-9)
    lr = np.maximum(np.linalg.norm(ur, axis=1), 1e-9)
    jac = np.zeros((len(obs), layout.size))
    col = 0
    for n, a in layout.receiver_idx:
        sel = ch == n
        jac[sel, col] = -k * ur[sel, a] / lr[sel]
        col += 1
    free = np.zeros((len(tied), 3), dtype=np.bool_)
    for n, a in layout.receiver_idx:
        free[n, a] = True
    for a in layout.emitter_axes:
        jac[:, col] = -k * ue[:, a] / le
        moves = ~free[ch, a]  # receiver coordinates that are not free ride with the emitter
        jac[moves, col] += -k * ur[moves, a] / lr[moves]
        col += 1
    for n in layout.delay_channels:
        jac[ch == n, col] = 1.0
        col += 1
    if layout.speed:
        jac[:, col] = -(le + lr) * k / g.speed_of_sound_m_s
    return jac


def _lm(obs, start, tied, layout, fs, theta, weights, max_iter) -> tuple[np.ndarray, int, bool]:
    """Weighted Levenberg-Marquardt with Marquardt (diagonal) damping."""
    lam = 1e-3
    g = _unpack(start, tied, layout, theta)
    r = _residuals(obs, g, fs)
    cost = float(np.sum(weights * r * r))
    for it in range(1, max_iter + 1):
        jac = _jacobian(obs, g, tied, layout, fs)
        jw = jac * weights[:, None]
        a = jw.T @ jac
        b = -(jw.T @ r)
        diag = np.diag(a).copy() + 1e-12
        improved = False
        for _try in range(10):
            try:
                step = np.linalg.solve(a + lam * np.diag(diag), b)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            trial = theta + step
            if layout.speed and not 100.0 < trial[-1] < 5000.0:
                lam *= 10.0
                continue
            g_trial = _unpack(start, tied, layout, trial)
            r_trial = _residuals(obs, g_trial, fs)
            new_cost = float(np.sum(weights * r_trial * r_trial))
            if new_cost <= cost:
                small = cost - new_cost <= 1e-12 * max(cost, 1e-30) or np.all(
                    np.abs(step) <= 1e-9 * (1 + np.abs(theta))
                )
                theta, g, r, cost = trial, g_trial, r_trial, new_cost
                lam = max(lam * 0.3, 1e-12)
                improved = not small
                break
            lam *= 10.0
        if not improved:
            return theta, it, True
    return theta, max_iter, False


def _robust_scale(r: np.ndarray, used: np.ndarray) -> float:
    x = r[used] if used.any() else r
    return max(1.4826 * float(np.median(np.abs(x - np.median(x)))), MIN_SCALE)


def _huber_weights(r: np.ndarray, scale: float, reject_sigma: float) -> np.ndarray:
    z = np.abs(r) / scale
    w = np.where(z <= HUBER_K, 1.0, HUBER_K / np.maximum(z, 1e-30))
    w[z > reject_sigma] = 0.0
    return w


def _uncertainty(obs, g, tied, layout, fs, r, weights) -> np.ndarray:
    """1-sigma from (J^T W J)^-1 * weighted residual variance; inf where undetermined."""
    jac = _jacobian(obs, g, tied, layout, fs)
    a = (jac * weights[:, None]).T @ jac
    dof = max(int((weights > 0).sum()) - layout.size, 1)
    sigma2 = float(np.sum(weights * r * r)) / dof
    d = np.sqrt(np.maximum(np.diag(a), 1e-300))
    scaled = a / np.outer(d, d)  # correlation-like scaling so the condition test is unit-free
    if np.linalg.cond(scaled) > 1e12:
        _raise_degenerate(scaled, layout)
    cov = np.linalg.inv(scaled) / np.outer(d, d)
    return np.sqrt(np.maximum(np.diag(cov), 0.0) * sigma2)


def _raise_degenerate(scaled: np.ndarray, layout: _Layout) -> None:
    vals, vecs = np.linalg.eigh(scaled)
    v = vecs[:, 0]
    names = [layout.names()[i] for i in np.argsort(-np.abs(v))[:3] if abs(v[i]) > 0.2]
    raise InputError(
        "these target positions cannot separate "
        + ", ".join(names)
        + "; spread the targets over more directions and ranges, or fix some of them "
        + f"(fixable: {', '.join(FIXABLE)})"
    )
