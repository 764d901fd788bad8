"""The ``[ranging]`` section of a profile: how a board with one or two listening transducers
(pulse-echo rangefinders such as TDK's DK-CH101, or a pair) turns echoes into a range, a
bearing and their variances (spiel_edge/pipeline/ranging.py, docs/hardware-ranging.md).
Boards with three or more listening channels use only its timing, iq_* and iq_sigma keys, to time
their matched echoes by the carrier phase with I/Q samples (pipeline/iq3d.py)."""

from __future__ import annotations

from dataclasses import dataclass

from spiel_edge.errors import ConfigError

TIMINGS = ("envelope", "iq")  # [ranging] timing
ECHO_CHOICES = ("first", "strongest")  # [ranging] echo


@dataclass(frozen=True)
class RangingSpec:
    """Timing of the chosen echo and its error model (all in samples of the envelope)."""

    timing: str = "envelope"  # "iq": the carrier phase refines the envelope's ToA (signal = "iq")
    echo: str = "first"  # which echo of a channel is the target: the first or the strongest
    # the envelope ToA is (1 - w) x the MEMG ToA + w x the data's interpolated peak: two
    # estimators whose biases differ from distance to distance average out (w fitted)
    peak_weight: float = 0.0
    # I/Q: the phase time (offset - phase) / (2 pi f) is the ToA modulo one wrap (1/f
    # samples); the wrap nearest t_env - (a + b t_env) is taken, drift = [a, b] (all fitted)
    iq_phase_offset_rad: float = 0.0
    iq_drift_samples: tuple = (0.0, 0.0)
    # I/Q: the wrap is taken from the envelope ToA; when that ToA sits within this share of a
    # wrap of the boundary between two wraps, the envelope timing is kept (wrap not trusted)
    iq_wrap_margin: float = 0.0
    # expected ToA error (samples), per timing: sqrt(a^2 + (b / alpha)^2 + (c x range_mm /
    # 100)^2 + (d x (1 - echo confidence))^2), as [a, b, c, d]; alpha: the echo's amplitude
    envelope_sigma: tuple = (0.3, 0.0, 0.0, 0.0)
    iq_sigma: tuple = (0.1, 0.0, 0.0, 0.0)
    # echo path = (ToA - delay) x mm per sample x range_scale: the clock and speed-of-sound
    # mismatch, fitted with the delay as one line over the training distances
    range_scale: float = 1.0
    # the 95 % interval a record's variance implies is calibrated on held-out positions
    # (tools/train/fit_ranging.py); two transducers: the std across their plane
    out_of_plane_std_deg: float = 30.0
    pair_tolerance_mm: float = 10.0  # two transducers: paths differ by <= baseline + this


def validate_ranging(spec: RangingSpec, signal: str, origin: str) -> None:
    def need(ok: bool, message: str) -> None:
        if not ok:
            raise ConfigError(f"{origin}: {message}")

    need(spec.timing in TIMINGS, f"ranging.timing must be one of {TIMINGS}, got {spec.timing!r}")
    need(
        spec.timing != "iq" or signal == "iq",
        "ranging.timing = 'iq' needs acquisition.signal = 'iq' (the carrier phase)",
    )
    need(
        spec.echo in ECHO_CHOICES, f"ranging.echo must be one of {ECHO_CHOICES}, got {spec.echo!r}"
    )
    need(0.0 <= spec.iq_wrap_margin < 0.5, "ranging.iq_wrap_margin must be in [0, 0.5)")
    need(
        len(spec.iq_drift_samples) == 2 and all(abs(v) <= 100 for v in spec.iq_drift_samples),
        f"ranging.iq_drift_samples must be 2 numbers in [-100, 100], got {list(spec.iq_drift_samples)}",
    )
    for key in ("envelope_sigma", "iq_sigma"):
        values = getattr(spec, key)
        need(
            len(values) == 4 and all(0.0 <= v <= 100.0 for v in values) and values[0] > 0,
            f"ranging.{key} must be 4 numbers in [0, 100] (the first > 0), got {list(values)}",
        )
    need(
        0.0 < spec.out_of_plane_std_deg <= 180.0, "ranging.out_of_plane_std_deg must be in (0, 180]"
    )
    need(
        0.5 <= spec.range_scale <= 2.0,
        f"ranging.range_scale must be in [0.5, 2], got {spec.range_scale}",
    )
    need(0.0 <= spec.pair_tolerance_mm <= 1000.0, "ranging.pair_tolerance_mm must be in [0, 1000]")
