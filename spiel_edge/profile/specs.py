"""The profile's frozen dataclass tree: one spec per TOML section, with the defaults a
section falls back to (loading, validation and TOML output are in ``schema``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from spiel_edge.profile.frame_section import FrameSpec
from spiel_edge.profile.ranging_section import RangingSpec
from spiel_edge.profile.track_section import TrackSpec

TOA_METHODS = ("mode", "mu", "half", "peak")
ASSOCIATION_METHODS = ("auto", "onnx", "geometric")
ECHO_TIMING_ESTIMATORS = ("none", "parabola", "log_parabola")
TOA_CORRECTIONS = ("auto", "onnx", "none")
SCENE_SELECTIONS = ("joint", "greedy")  # [scene] selection (pipeline/stages/scene.py)
SIGNALS = ("envelope", "rf", "iq")  # [acquisition] signal


@dataclass(frozen=True)
class AcquisitionSpec:
    sample_rate_hz: float = 22000.0
    n_samples: int = 64
    signal: str = "envelope"  # "envelope", "rf" (envelope computed here) or "iq" (pairs)
    carrier_hz: float = 175000.0  # rf: demodulated at; iq: the phase's rate (any sample rate)


@dataclass(frozen=True)
class Geometry:
    channels_mm: np.ndarray
    emitter_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    facing: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    listening: np.ndarray | None = None
    delay_samples: np.ndarray | None = None
    speed_of_sound_m_s: float = 343.0

    @property
    def n_channels(self) -> int:
        return int(self.channels_mm.shape[0])

    def listening_mask(self) -> np.ndarray:
        if self.listening is None:
            return np.ones(self.n_channels, dtype=np.bool_)
        return self.listening

    def delays(self) -> np.ndarray:
        if self.delay_samples is None:
            return np.zeros(self.n_channels)
        return self.delay_samples

    def echo_paths_mm(self, position_mm: np.ndarray) -> np.ndarray:
        """Per channel the echo path emitter -> target -> channel (mm) of a point target."""
        p = np.asarray(position_mm, dtype=np.float64)
        return np.linalg.norm(p - self.emitter_mm) + np.linalg.norm(p - self.channels_mm, axis=1)


@dataclass(frozen=True)
class PreprocessSpec:
    background_subtraction: bool = True
    blind_zone_samples: int = 0


@dataclass(frozen=True)
class DetectSpec:
    threshold: float = 30.0
    hysteresis: float = 0.5
    min_amplitude: float = 60.0
    max_echoes: int = 6


@dataclass(frozen=True)
class MemgSpec:
    max_iterations: int = 30
    mu_window: float = 3.0
    toa: str = "mode"
    split_merged: bool = False  # split merged two-echo humps (pipeline/stages/split.py)
    split_min_sigma: float = 2.0  # only components at least this wide (samples) are tried
    split_max_cost_ratio: float = 1.0  # keep two when they leave at most this share of one's
    window_before: int = 5  # samples fitted before an echo's detection (its leading edge) ...
    window_after: int = 6  # ... and after it; 5/6 run compiled, others in memg._fit_windowed


@dataclass(frozen=True)
class AssociateSpec:
    method: str = "auto"
    tolerance_mm: float = 12.0
    max_residual_mm: float = 15.0
    missing_penalty_mm: float = 10.0
    strength_weight_mm: float = 0.0
    range_weight: float = 0.0
    min_channels: int = 3


@dataclass(frozen=True)
class LocateSpec:
    """Per matched echo, its expected ToA error (whose inverse weighs its channel in the solve)
    and a ToA correction for background interference; see pipeline/stages/echo_quality.py."""

    toa_sigma_samples: float = 1.0
    toa_sigma_per_background: float = 0.0
    toa_sigma_alpha_counts: float = 0.0
    toa_shift_background_after: float = 0.0
    toa_shift_background_before: float = 0.0


@dataclass(frozen=True)
class SceneSpec:
    """Several targets per acquisition and their uncertainty; see docs/scene.md."""

    max_targets: int = 1
    selection: str = "joint"  # "joint" (pipeline/stages/joint.py) or "greedy" choice of the targets
    max_cost_mm: float = 0.0  # a further target needs an association cost <= this (joint: birth)
    share_penalty_mm: float = 40.0  # cost of reusing an echo another target took
    missing_penalty_mm: float = 10.0  # joint: cost of a channel left out (replaces associate's)
    keep_best: bool = True  # joint: the K = 1 pick is always the first target
    extra_min_channels: int = 3  # channels a further target must use (capped at the listening)
    share_tolerance_mm: float = 6.0  # two targets share an echo within this of the prediction
    min_separation_mm: float = 25.0  # a target nearer than this to a better one is dropped
    double_tolerance_mm: float = 20.0  # target -> board -> target paths within this are dropped
    covariance_scale: float = 1.0  # scales the linearised covariance's standard deviations
    covariance_floor_mm: float = 0.0  # std added in every direction (unmodelled errors)
    covariance_scale_no_background: float = 1.0  # covariance_scale when no background is given
    static_model: str = ""  # file in spiel_edge/models (or a path): used without a background
    static_mad_factor: float = 0.0  # stand-in background = median + this x MAD of the model
    # per-target error model of the covariance (pipeline/stages/error_model.py): empty = off,
    # else [w0, w_range, w_angle, w_log_alpha, w_residual, w_miss, factor_bg, factor_none]
    error_model: tuple = ()


MAX_TARGETS_LIMIT = 16  # also in profile/ranges.py (scene.max_targets)


@dataclass(frozen=True)
class EchoTimingSpec:
    """Per matched echo, the ToA from the power-domain background-free envelope and a learned
    correction; see pipeline/stages/echo_timing.py. ``delay_shift_samples`` (one per channel, or
    empty for none) is added to the geometry's delays when the estimator is on."""

    estimator: str = "none"
    half_window: int = 2
    toa_correction: str = "none"
    delay_shift_samples: tuple = ()


@dataclass(frozen=True)
class Profile:
    name: str
    geometry: Geometry
    acquisition: AcquisitionSpec = AcquisitionSpec()
    preprocess: PreprocessSpec = PreprocessSpec()
    detect: DetectSpec = DetectSpec()
    memg: MemgSpec = MemgSpec()
    associate: AssociateSpec = AssociateSpec()
    locate: LocateSpec = LocateSpec()
    scene: SceneSpec = SceneSpec()
    echo_timing: EchoTimingSpec = EchoTimingSpec()
    track: TrackSpec = TrackSpec()
    frame: FrameSpec = FrameSpec()
    ranging: RangingSpec = RangingSpec()
    description: str = ""

    @property
    def mm_per_sample(self) -> float:
        """Echo path length (mm) travelled in one sample period."""
        return self.geometry.speed_of_sound_m_s * 1000.0 / self.acquisition.sample_rate_hz

    def replace(self, **sections: Any) -> Profile:
        return dataclasses.replace(self, **sections)
