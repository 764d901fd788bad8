"""What the virtual board measures: replayed real recordings, or a physical echo model.

A scene returns one SceneFrame per acquisition: uint16 envelope samples (channels, samples),
the target-free background of the same pose (what the host subtracts) and the ground truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from spiel_edge.data import load_subset
from spiel_edge.errors import ConfigError
from spiel_edge.profile.schema import Geometry, load_profile
from spiel_edge.sim.movers import MoverPaths

U16_MAX = 65535


@dataclass(frozen=True)
class SceneFrame:
    samples: np.ndarray  # (channels, n_samples) uint16
    background: np.ndarray | None  # (channels, n_samples) uint16, the same pose without target
    truth_mm: np.ndarray | None  # (3,) position of the target, None when unknown
    truth_targets_mm: np.ndarray | None = None  # (K, 3) every target, when there are several
    iq: np.ndarray | None = None  # (channels, n_samples, 2) int16 (q, i), when asked for


class ReplayScene:
    """The vendored spiel-icra23 subset, looped (in recorded order, or shuffled)."""

    sample_rate_hz = 22000

    def __init__(self, *, shuffle: bool = False, seed: int = 0):
        data = load_subset()
        self._frames = np.clip(np.rint(data.frames), 0, U16_MAX).astype(np.uint16)
        self._backgrounds = np.clip(np.rint(data.backgrounds), 0, U16_MAX).astype(np.uint16)
        self._truth = data.truth_mm
        self._order = np.arange(len(data))
        if shuffle:
            np.random.default_rng(seed).shuffle(self._order)
        self.n_channels, self.n_samples = self._frames.shape[1:]

    def supports(self, n_samples: int) -> bool:
        return n_samples == self.n_samples

    def frame(self, index: int, n_samples: int, time_s: float) -> SceneFrame:
        del n_samples, time_s  # recordings have one length and no clock
        k = self._order[index % len(self._order)]
        return SceneFrame(self._frames[k], self._backgrounds[k], self._truth[k])


@dataclass(frozen=True)
class EchoModel:
    """Envelope model of one emitter and N receivers; amplitudes in ADC counts."""

    reflectivity: float = 1.1e7  # echo amplitude x (emitter distance x receiver distance), mm^2
    sigma: float = 1.6  # pulse width (samples) of the EMG-shaped envelope
    eta: float = 0.8  # its skew: a slower decay than rise, like the CH101's envelope
    ring_down: float = 10000.0  # emitter ring-down peak on the emitting channel
    ring_down_tau: float = 1.6  # its decay time constant (samples)
    crosstalk: float = 300.0  # direct emitter -> receiver pulse amplitude
    clutter_mm: float = 250.0  # a static reflector (the mount) at this echo path length
    clutter: float = 250.0  # and its amplitude


class EchoModelScene:
    """Point targets in front of the array; arrival times from the geometry and the speed of
    sound, exactly as the pipeline's path model: ToA = path / mm_per_sample + delay."""

    def __init__(
        self,
        geometry: Geometry,
        *,
        sample_rate_hz: float = 22000.0,
        n_samples: int = 64,
        targets_mm: np.ndarray | None = None,
        orbit: tuple[float, float, float] = (60.0, 150.0, 8.0),
        noise: float = 20.0,
        speed_of_sound_m_s: float | None = None,
        model: EchoModel = EchoModel(),
        seed: int = 0,
        movers=None,
        carrier_hz: float = 175000.0,
    ):
        self.geometry = geometry
        self.sample_rate_hz = int(round(sample_rate_hz))
        self.n_channels, self.n_samples = geometry.n_channels, n_samples
        self.targets = None if targets_mm is None else np.atleast_2d(np.asarray(targets_mm, float))
        self.orbit = orbit
        self.movers = movers  # sim/movers.py MoverPaths: targets on smooth random paths
        self.noise = noise
        self.speed = speed_of_sound_m_s or geometry.speed_of_sound_m_s
        self.model = model
        self.carrier_hz = carrier_hz
        self._rng = np.random.default_rng(seed)
        self._mode_offset = emg_mode(model.sigma, model.eta)
        self._backgrounds: dict[int, np.ndarray] = {}

    @property
    def mm_per_sample(self) -> float:
        return self.speed * 1000.0 / self.sample_rate_hz

    def supports(self, n_samples: int) -> bool:
        return 8 <= n_samples <= 4096

    def target_positions(self, time_s: float) -> np.ndarray:
        if self.movers is not None:
            moving = self.movers.positions(time_s)
            return moving if self.targets is None else np.vstack([self.targets, moving])
        if self.targets is not None:
            return self.targets
        radius, height, period = self.orbit
        angle = 2 * math.pi * time_s / period if period > 0 else 0.0
        return np.array([[radius * math.cos(angle), radius * math.sin(angle), height]])

    def place(self, targets_mm: ArrayLike) -> None:
        """Move the targets (K, 3) mm, z > 0: what a robot holding the target does between the
        positions of a guided calibration. Acquisitions made from now on see them."""
        arr = np.atleast_2d(np.asarray(targets_mm, dtype=np.float64))
        if (
            arr.ndim != 2
            or arr.shape[1] != 3
            or not len(arr)
            or not np.all(np.isfinite(arr))
            or np.any(arr[:, 2] <= 0)
        ):
            raise ConfigError(
                f"targets must be finite (x, y, z) rows in mm with z > 0, got {targets_mm!r}"
            )
        self.targets = arr

    iq_supported = True  # the virtual board may stream I16_IQ from this scene

    def frame(self, index: int, n_samples: int, time_s: float, *, iq: bool = False) -> SceneFrame:
        del index
        background = self.background(n_samples)
        targets = self.target_positions(time_s)
        clean = background.astype(np.float64)
        for p in targets:
            clean += self._echoes(p, n_samples)
        noisy = clean + self._rng.normal(0.0, self.noise, clean.shape) if self.noise else clean
        samples = np.clip(np.rint(noisy), 0, U16_MAX).astype(np.uint16)
        pairs = self._iq(samples, targets, n_samples) if iq else None
        return SceneFrame(samples, background, targets[0].copy(), targets.copy(), pairs)

    def _iq(self, amplitude: np.ndarray, targets: np.ndarray, n_samples: int) -> np.ndarray:
        """I/Q as the CH101 gives them: every component of the echo model (ring-down,
        crosstalk, the mount, each target's echo) is a carrier at ``carrier_hz`` delayed by its
        time of arrival; mixing down with the carrier leaves each as its envelope times
        exp(-j 2 pi f_c tau), and the phase of their sum is the I/Q's phase. The magnitude is
        the envelope stream's own sample: as on the CH101, whose amplitude data is the rounded
        magnitude of its I/Q, round(|i + jq|) equals the U16 envelope of the same acquisition
        (each (i, q) is the int16 pair nearest the phase with that rounded magnitude; values
        above 32767 are clipped)."""
        phasor = self._background_phasor(n_samples).copy()
        for p in targets:
            toa_s = self.arrival_samples(p) / self.sample_rate_hz
            turn = np.exp(-2j * math.pi * self.carrier_hz * toa_s)
            phasor += self._echoes(p, n_samples) * turn[:, None]
        angle = np.angle(phasor)
        mag = np.minimum(amplitude.astype(np.float64), 32767.0)
        i0, q0 = np.rint(mag * np.cos(angle)), np.rint(mag * np.sin(angle))
        best_i, best_q, best_err = i0, q0, np.full(mag.shape, np.inf)
        for di in (0.0, -1.0, 1.0):
            for dq in (0.0, -1.0, 1.0):
                i, q = np.clip(i0 + di, -32768, 32767), np.clip(q0 + dq, -32768, 32767)
                err = np.abs(np.hypot(i, q) - mag)
                better = err < best_err - 1e-9
                best_i, best_q = np.where(better, i, best_i), np.where(better, q, best_q)
                best_err = np.minimum(err, best_err)
        out = np.empty(mag.shape + (2,), dtype=np.int16)
        out[..., 0], out[..., 1] = best_q, best_i  # (q, i), SonicLib's order
        return out

    def _background_phasor(self, n_samples: int) -> np.ndarray:
        """The target-free components mixed down (see ``_iq``), complex (channels, samples)."""
        g, m = self.geometry, self.model
        t = np.arange(n_samples, dtype=np.float64)
        out = np.zeros((g.n_channels, n_samples), dtype=np.complex128)
        direct = np.linalg.norm(g.channels_mm - g.emitter_mm, axis=1)

        def turn(samples: float) -> complex:
            return np.exp(-2j * math.pi * self.carrier_hz * samples / self.sample_rate_hz)

        for n in range(g.n_channels):
            if direct[n] < 1e-6:
                ring = m.ring_down * np.exp(-np.maximum(t - 2.0, 0.0) / m.ring_down_tau) * (t >= 2)
                out[n] += ring * turn(2.0)
            else:
                mode = direct[n] / self.mm_per_sample + 2.0
                out[n] += self._pulse(t, mode, m.crosstalk) * turn(mode)
            mode = m.clutter_mm / self.mm_per_sample + g.delays()[n]
            out[n] += self._pulse(t, mode, m.clutter) * turn(mode)
        return out

    def background(self, n_samples: int) -> np.ndarray:
        """Ring-down, crosstalk and the static reflector: the scene without targets."""
        if n_samples not in self._backgrounds:
            g, m = self.geometry, self.model
            t = np.arange(n_samples, dtype=np.float64)
            out = np.zeros((g.n_channels, n_samples))
            direct = np.linalg.norm(g.channels_mm - g.emitter_mm, axis=1)
            for n in range(g.n_channels):
                if direct[n] < 1e-6:  # the emitting channel hears its own ring-down
                    out[n] += (
                        m.ring_down * np.exp(-np.maximum(t - 2.0, 0.0) / m.ring_down_tau) * (t >= 2)
                    )
                else:
                    out[n] += self._pulse(t, direct[n] / self.mm_per_sample + 2.0, m.crosstalk)
                out[n] += self._pulse(
                    t, m.clutter_mm / self.mm_per_sample + g.delays()[n], m.clutter
                )
            self._backgrounds[n_samples] = np.clip(np.rint(out), 0, U16_MAX).astype(np.uint16)
        return self._backgrounds[n_samples]

    def arrival_samples(self, p: np.ndarray) -> np.ndarray:
        """Echo time of arrival per channel (samples), delays included."""
        g = self.geometry
        return g.echo_paths_mm(p) / self.mm_per_sample + g.delays()

    def _echoes(self, p: np.ndarray, n_samples: int) -> np.ndarray:
        g, m = self.geometry, self.model
        t = np.arange(n_samples, dtype=np.float64)
        d_tx = max(float(np.linalg.norm(p - g.emitter_mm)), 1.0)
        d_rx = np.maximum(np.linalg.norm(p - g.channels_mm, axis=1), 1.0)
        toa = self.arrival_samples(p)
        out = np.zeros((g.n_channels, n_samples))
        for n in range(g.n_channels):
            if g.listening_mask()[n]:
                out[n] = self._pulse(t, toa[n], m.reflectivity / (d_tx * d_rx[n]))
        return out

    def _pulse(self, t: np.ndarray, mode: float, amplitude: float) -> np.ndarray:
        """An EMG envelope whose maximum (``amplitude``) is at ``mode``."""
        m = self.model
        u = (t - (mode - self._mode_offset)) / m.sigma
        shape = np.exp(-0.5 * u * u) * (1.0 + erf_array(m.eta * u / math.sqrt(2.0)))
        return amplitude * shape / self._peak

    @property
    def _peak(self) -> float:
        u = self._mode_offset / self.model.sigma
        return math.exp(-0.5 * u * u) * (1.0 + math.erf(self.model.eta * u / math.sqrt(2.0)))


def erf_array(x: np.ndarray) -> np.ndarray:
    return np.vectorize(math.erf, otypes=[np.float64])(x)


def emg_mode(sigma: float, eta: float) -> float:
    """Offset of the EMG maximum from its mu (samples), found on a fine grid."""
    u = np.linspace(-3.0, 3.0, 60001)
    shape = np.exp(-0.5 * u * u) * (1.0 + erf_array(eta * u / math.sqrt(2.0)))
    return float(u[np.argmax(shape)] * sigma)


def parse_targets(text: str) -> np.ndarray | None:
    """``"x,y,z;x,y,z"`` (mm) -> (K, 3), or None for an empty string."""
    if not text.strip():
        return None
    try:
        rows = [[float(v) for v in item.split(",")] for item in text.split(";") if item.strip()]
        arr = np.array(rows, dtype=np.float64)
    except ValueError:
        arr = np.zeros((0, 0))
    if arr.ndim != 2 or arr.shape[1] != 3 or not len(arr) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"targets must be 'x,y,z;x,y,z' in mm, got {text!r}")
    if np.any(arr[:, 2] <= 0):
        raise ConfigError(f"targets must be in front of the array (z > 0), got {text!r}")
    return arr


def parse_orbit(text: str) -> tuple[float, float, float]:
    try:
        radius, height, period = (float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"orbit must be 'radius_mm,height_mm,period_s', got {text!r}") from None
    if height <= 0 or radius < 0 or period < 0:
        raise ConfigError(f"orbit needs radius >= 0, height > 0, period >= 0, got {text!r}")
    return radius, height, period


def build_scene(options) -> ReplayScene | EchoModelScene:
    """The scene a SimOptions asks for."""
    if options.scene == "replay":
        return ReplayScene(shuffle=options.shuffle, seed=options.seed)
    profile = load_profile(options.profile)
    return EchoModelScene(
        profile.geometry,
        sample_rate_hz=profile.acquisition.sample_rate_hz,
        n_samples=profile.acquisition.n_samples,
        targets_mm=parse_targets(options.targets),
        orbit=parse_orbit(options.orbit),
        noise=options.noise,
        speed_of_sound_m_s=options.speed or None,
        seed=options.seed,
        movers=MoverPaths(options.movers, seed=options.seed) if options.movers else None,
        carrier_hz=profile.acquisition.carrier_hz,
    )
