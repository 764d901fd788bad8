"""The allowed range of every bounded setting, in one table shared by device profiles and the
board's stored config, so both say the same thing about the same key."""

from __future__ import annotations

import math

from spiel_edge.errors import ConfigError

# "section.key" -> (low, high), inclusive
RANGES: dict[str, tuple[float, float]] = {
    "acquisition.n_samples": (8, 4096),
    "acquisition.sample_rate_hz": (1e3, 1e7),
    "acquisition.carrier_hz": (0.0, 5e6),
    "preprocess.blind_zone_samples": (0, 4096),
    "detect.threshold": (1e-6, 1e6),
    "detect.min_amplitude": (0.0, 1e6),
    "associate.tolerance_mm": (0.0, 1000.0),
    "associate.max_residual_mm": (1e-3, 1000.0),
    "associate.missing_penalty_mm": (0.0, 1000.0),
    "associate.strength_weight_mm": (0.0, 1000.0),
    "associate.range_weight": (0.0, 100.0),
    "associate.min_channels": (3, 64),
    "locate.toa_sigma_samples": (1e-6, 100.0),
    "locate.toa_sigma_per_background": (0.0, 100.0),
    "locate.toa_sigma_alpha_counts": (0.0, 1e6),
    "locate.toa_shift_background_after": (-5.0, 5.0),
    "locate.toa_shift_background_before": (-5.0, 5.0),
    "geometry.speed_of_sound_m_s": (200.0, 2000.0),
    "detect.hysteresis": (0.0, 1.0),
    "detect.max_echoes": (1, 16),
    "memg.max_iterations": (1, 200),
    "memg.mu_window": (0.5, 20.0),
    "memg.split_min_sigma": (0.4, 6.0),
    "memg.split_max_cost_ratio": (0.01, 1.0),
    "scene.max_targets": (1, 16),
    "scene.max_cost_mm": (-1000.0, 1000.0),
    "scene.share_penalty_mm": (0.0, 1000.0),
    "scene.extra_min_channels": (3, 64),
    "scene.missing_penalty_mm": (0.0, 1000.0),
    "scene.share_tolerance_mm": (0.0, 100.0),
    "scene.min_separation_mm": (0.0, 1000.0),
    "scene.double_tolerance_mm": (0.0, 100.0),
    "scene.covariance_scale": (0.01, 100.0),
    "scene.covariance_floor_mm": (0.0, 1000.0),
    "scene.covariance_scale_no_background": (0.01, 100.0),
    "scene.static_mad_factor": (0.0, 10.0),
    "echo_timing.half_window": (1, 8),
    "track.acceleration_mm_s2": (0.0, 1e5),
    "track.measurement_floor_mm": (0.01, 100.0),
    "track.fallback_sigma_mm": (0.1, 1000.0),
    "track.initial_speed_mm_s": (0.0, 1e4),
    "track.gate_chi2": (1.0, 1000.0),
    "track.confirm_hits": (1, 50),
    "track.confirm_window": (1, 50),
    "track.max_misses": (1, 1000),
    "track.max_tracks": (1, 64),
    "track.max_gap_s": (0.001, 3600.0),
    "track.imm_static_noise_mm": (0.0, 1e4),
    "track.imm_switch_probability": (0.0, 0.5),
    "track.imm_static_share": (0.0, 1.0),
    "frame.translation_m": (-100.0, 100.0),  # each coordinate
    "frame.rotation_rpy_deg": (-360.0, 360.0),  # each angle
    "track.running_background_window": (0, 256),
    "track.running_background_guard_samples": (0.0, 64.0),
}


# any other number a profile, calibration or board config holds (a key added later, before it
# gets its own row above): finite and within this magnitude, so no value can make every
# acquisition fail silently
GENERIC_LIMIT = 1e6


def check_number(key: str, value: object, origin: str) -> None:
    """Every number: finite; within RANGES[key] when listed, else within +-GENERIC_LIMIT.
    ConfigError naming the key otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    if key in RANGES:
        check_range(key, value, origin)
        return
    if not math.isfinite(value) or abs(value) > GENERIC_LIMIT:
        raise ConfigError(
            f"{origin}: {key} must be a finite number in [-{GENERIC_LIMIT:g}, "
            f"{GENERIC_LIMIT:g}], got {value!r}"
        )


def in_range(key: str, value: object) -> bool:
    low, high = RANGES[key]
    return isinstance(value, (int, float)) and not isinstance(value, bool) and low <= value <= high


def check_range(key: str, value: object, origin: str) -> None:
    """ConfigError naming the key, its range and the value when ``value`` is outside it."""
    if not in_range(key, value):
        low, high = RANGES[key]
        raise ConfigError(f"{origin}: {key} must be a number in [{low:g}, {high:g}], got {value!r}")
