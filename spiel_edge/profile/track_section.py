"""The ``[track]`` section of a profile: the multi-target tracker's settings (spiel_edge/track/,
docs/tracking.md); ranges in profile/ranges.py."""

from __future__ import annotations

from dataclasses import dataclass, fields

from spiel_edge.errors import ConfigError
from spiel_edge.profile.ranges import check_range


@dataclass(frozen=True)
class TrackSpec:
    """Constant-velocity Kalman filter per track, Mahalanobis gate, one global assignment per
    acquisition, M-of-N confirmation, deletion after misses, a cap on tracks."""

    acceleration_mm_s2: float = 1000.0  # white-noise acceleration std (process noise)
    measurement_floor_mm: float = 3.0  # added in quadrature to every target's covariance
    fallback_sigma_mm: float = 20.0  # target std when its covariance is missing or non-finite
    initial_speed_mm_s: float = 300.0  # velocity std of a new track
    gate_chi2: float = 16.27  # squared Mahalanobis gate (3 dof; 16.27 = 99.9 %)
    confirm_hits: int = 3  # M: a tentative track is confirmed after M hits ...
    confirm_window: int = 5  # ... within its first N acquisitions, else dropped
    max_misses: int = 10  # a confirmed track is deleted after this many misses in a row
    max_tracks: int = 16  # tentative and confirmed tracks at once (births beyond are dropped)
    max_gap_s: float = 1.0  # a longer gap between acquisitions (or time going back) restarts
    # interacting multiple model (track/imm.py): a near-static model beside the constant-velocity
    # one; both imm_switch_probability and imm_static_share at 0 turn it off (CV filter alone)
    imm_static_noise_mm: float = 1.0  # static model: position random walk, mm per sqrt(s)
    imm_switch_probability: float = 0.3  # per acquisition, static <-> moving (chosen on training)
    imm_static_share: float = 0.5  # the static model's probability at a track's birth
    # without a background capture: per-sample median of this many recent acquisitions, not
    # updated at confirmed tracks' echoes (runtime/static_scene.py); 0 = off
    running_background_window: int = 0
    running_background_guard_samples: float = 4.0  # half width kept out around a track's echo


def validate_track(spec: TrackSpec, origin: str) -> None:
    """Every key within its range (profile/ranges.py), and M <= N."""
    for f in fields(spec):
        check_range(f"track.{f.name}", getattr(spec, f.name), origin)
    if spec.confirm_hits > spec.confirm_window:
        raise ConfigError(
            f"{origin}: track.confirm_hits ({spec.confirm_hits}) must be <= "
            f"track.confirm_window ({spec.confirm_window})"
        )
