"""Device profiles: the hardware geometry and timing plus the pipeline's tuning, from TOML.

A profile is one frozen dataclass tree. Built-in profiles live in ``spiel_edge/profile/builtin/``;
users copy one and edit it. A calibration file is a partial profile (usually ``[geometry]``
only) applied over a base profile.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from spiel_edge.errors import ConfigError
from spiel_edge.profile.frame_section import FrameSpec, validate_frame
from spiel_edge.profile.geometry_checks import check_geometry
from spiel_edge.profile.ranges import RANGES, check_number, check_range
from spiel_edge.profile.ranging_section import RangingSpec, validate_ranging
from spiel_edge.profile.specs import (
    ASSOCIATION_METHODS,
    ECHO_TIMING_ESTIMATORS,
    SCENE_SELECTIONS,
    SIGNALS,
    TOA_CORRECTIONS,
    TOA_METHODS,
    AcquisitionSpec,
    AssociateSpec,
    DetectSpec,
    EchoTimingSpec,
    Geometry,
    LocateSpec,
    MemgSpec,
    PreprocessSpec,
    Profile,
    SceneSpec,
)
from spiel_edge.profile.track_section import TrackSpec, validate_track
from spiel_edge.safety.guard import read_config_text, shorten
from spiel_edge.safety.limits import load_npz_bounded, loads_toml

log = logging.getLogger(__name__)

SECTIONS = {
    "acquisition": AcquisitionSpec,
    "preprocess": PreprocessSpec,
    "detect": DetectSpec,
    "memg": MemgSpec,
    "associate": AssociateSpec,
    "locate": LocateSpec,
    "scene": SceneSpec,
    "echo_timing": EchoTimingSpec,
    "track": TrackSpec,
    "frame": FrameSpec,
    "ranging": RangingSpec,
}
_GEOMETRY_KEYS = {f.name for f in dataclasses.fields(Geometry)}


def builtin_profiles() -> list[str]:
    folder = resources.files("spiel_edge") / "profile" / "builtin"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_profile(name_or_path: str | Path = "spiel-icra23") -> Profile:
    """Load a built-in profile by name, or a profile TOML file by path."""
    text, origin = _read_profile_text(name_or_path)
    data = loads_toml(text, ConfigError, shorten(origin))
    profile = profile_from_dict(data, origin=origin)
    check_static_model(profile.scene.static_model, shorten(origin))
    return profile


def apply_calibration(profile: Profile, path: str | Path) -> Profile:
    """Overlay a calibration (a partial profile TOML, e.g. only [geometry]) on ``profile``."""
    path = Path(path)
    data = loads_toml(read_config_text(path, "calibration"), ConfigError, shorten(path))
    merged = profile_to_dict(profile)
    for key, value in data.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key].update(value)
        else:
            merged[key] = value
    calibrated = profile_from_dict(merged, origin=str(path))
    if calibrated.scene.static_model != profile.scene.static_model:
        check_static_model(calibrated.scene.static_model, shorten(path))
    return calibrated


def check_static_model(name: str, origin: str) -> None:
    """``[scene] static_model``, when it names a file that exists: a .npz archive within its
    bound holding numeric ``median`` and ``mad`` arrays, checked by their headers at load (a
    FIFO, a .npy, a zip bomb or a string array is refused here, naming the key)."""
    if not name:
        return
    path = Path(name)  # as pipeline/static_scene.model_path finds it
    if not (path.is_absolute() or path.exists()):
        path = Path(str(resources.files("spiel_edge") / "models" / name))
    if not os.path.lexists(path):
        return  # the pipeline says it runs without one
    try:
        members = load_npz_bounded(path, "static model", ConfigError, headers_only=True)
    except ConfigError as exc:
        raise ConfigError(f"{origin}: scene.static_model: {exc}") from None
    missing = {"median", "mad"} - set(members)
    if missing:
        raise ConfigError(
            f"{origin}: scene.static_model {shorten(path)}: no {' or '.join(sorted(missing))} array"
        )


def resolve_profile(name_or_path: str | Path, calibration: str | Path | None = None) -> Profile:
    """The profile ``name_or_path`` with the calibration file (if any) applied over it: the one
    way every command and the service load "profile + calibration"."""
    profile = load_profile(name_or_path)
    return apply_calibration(profile, calibration) if calibration else profile


def _read_profile_text(name_or_path: str | Path) -> tuple[str, str]:
    candidate = Path(name_or_path)
    if candidate.suffix == ".toml" or candidate.exists():
        return read_config_text(candidate, "profile"), str(candidate)
    name = str(name_or_path)
    if name not in builtin_profiles():
        raise ConfigError(
            f"unknown profile {name!r}; built-in profiles: {', '.join(builtin_profiles())} "
            "(or give a path to a .toml file)"
        )
    return (
        resources.files("spiel_edge") / "profile" / "builtin" / f"{name}.toml"
    ).read_text(), name


def profile_from_dict(data: dict[str, Any], *, origin: str = "profile") -> Profile:
    data = dict(data)
    allowed = {"name", "description", "geometry", *SECTIONS}
    unknown = set(data) - allowed
    if unknown:
        raise ConfigError(f"{origin}: unknown key(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
    sections = {key: _section(origin, key, cls, data.get(key, {})) for key, cls in SECTIONS.items()}
    geometry = _geometry(origin, data.get("geometry"))
    profile = Profile(
        name=str(data.get("name", Path(origin).stem)),
        description=str(data.get("description", "")),
        geometry=geometry,
        **sections,
    )
    validate_profile(profile, origin)
    return profile


def _section(origin: str, key: str, cls: type, values: Any) -> Any:
    if not isinstance(values, dict):
        raise ConfigError(f"{origin}: [{key}] must be a table")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(values) - set(fields)
    if unknown:
        raise ConfigError(
            f"{origin}: unknown key(s) {sorted(unknown)} in [{key}]; allowed: {sorted(fields)}"
        )
    defaults = cls()
    converted = {}
    for name, value in values.items():
        expected = type(getattr(defaults, name))
        if expected is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if expected is tuple and isinstance(value, list):
            value = _number_tuple(origin, f"{key}.{name}", value)
        if not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
            raise ConfigError(f"{origin}: {key}.{name} must be {expected.__name__}, got {value!r}")
        if not isinstance(value, tuple):
            check_number(f"{key}.{name}", value, origin)
        elif f"{key}.{name}" not in RANGES:  # listed ones: their section's validator says more
            for item in value:
                check_number(f"{key}.{name}", item, origin)
        converted[name] = value
    return cls(**converted)


def _number_tuple(origin: str, where: str, values: list) -> tuple:
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        raise ConfigError(f"{origin}: {where} must be a list of numbers, got {values!r}")
    return tuple(float(v) for v in values)


def _geometry(origin: str, values: Any) -> Geometry:
    if not isinstance(values, dict) or "channels_mm" not in values:
        raise ConfigError(
            f"{origin}: [geometry] with channels_mm (one [x, y, z] per channel) is required"
        )
    unknown = set(values) - _GEOMETRY_KEYS
    if unknown:
        raise ConfigError(
            f"{origin}: unknown key(s) {sorted(unknown)} in [geometry]; allowed: {sorted(_GEOMETRY_KEYS)}"
        )
    channels = _array(origin, "geometry.channels_mm", values["channels_mm"], ndim=2)
    n = channels.shape[0]
    kwargs: dict[str, Any] = {"channels_mm": channels}
    if "emitter_mm" in values:
        kwargs["emitter_mm"] = _array(
            origin, "geometry.emitter_mm", values["emitter_mm"], shape=(3,)
        )
    if "facing" in values:
        facing = _array(origin, "geometry.facing", values["facing"], shape=(3,))
        norm = float(np.linalg.norm(facing))
        if norm == 0:
            raise ConfigError(f"{origin}: geometry.facing must be a non-zero vector")
        kwargs["facing"] = facing / norm
    if "listening" in values:
        listening = values["listening"]
        if not (
            isinstance(listening, list)
            and len(listening) == n
            and all(isinstance(v, bool) for v in listening)
        ):
            raise ConfigError(f"{origin}: geometry.listening must be {n} booleans, one per channel")
        kwargs["listening"] = np.array(listening, dtype=np.bool_)
    if "delay_samples" in values:
        kwargs["delay_samples"] = _array(
            origin, "geometry.delay_samples", values["delay_samples"], shape=(n,)
        )
    if "speed_of_sound_m_s" in values:
        speed = values["speed_of_sound_m_s"]
        check_range("geometry.speed_of_sound_m_s", speed, origin)
        kwargs["speed_of_sound_m_s"] = float(speed)
    return Geometry(**kwargs)


def _array(
    origin: str, key: str, value: Any, *, ndim: int | None = None, shape: tuple | None = None
) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{origin}: {key} must be numbers, got {value!r}") from exc
    if ndim == 2 and (arr.ndim != 2 or arr.shape[1] != 3):
        raise ConfigError(
            f"{origin}: {key} must be a list of [x, y, z] rows, got shape {arr.shape}"
        )
    if shape is not None and arr.shape != shape:
        raise ConfigError(f"{origin}: {key} must have shape {list(shape)}, got {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{origin}: {key} must be finite numbers")
    arr.setflags(write=False)
    return arr


def validate_profile(p: Profile, origin: str = "profile") -> None:
    """Cross-field rules; raises ConfigError naming the key and the allowed range."""

    def need(ok: bool, msg: str) -> None:
        if not ok:
            raise ConfigError(f"{origin}: {msg}")

    a, g = p.acquisition, p.geometry
    check_range("acquisition.sample_rate_hz", a.sample_rate_hz, origin)
    check_range("acquisition.n_samples", a.n_samples, origin)
    need(a.signal in SIGNALS, f"acquisition.signal must be one of {SIGNALS}, got {a.signal!r}")
    if a.signal == "rf":
        need(
            0 < a.carrier_hz < a.sample_rate_hz / 2,
            "acquisition.carrier_hz must be below half the sample rate for signal = 'rf'",
        )
    if a.signal == "iq":  # baseband pairs: any sample rate (the CH101 samples at carrier / 2)
        need(a.carrier_hz > 0, "acquisition.carrier_hz must be > 0 for signal = 'iq'")
    n_listen = int(g.listening_mask().sum())
    need(n_listen >= 1, "geometry needs at least 1 listening channel, has 0")
    # 1 or 2 listening transducers: range (and bearing), pipeline/ranging.py; 3 or more with
    # I/Q: 3-D positions timed by the carrier phase, pipeline/iq3d.py
    check_geometry(g, a.n_samples, origin)
    _validate_window(p.memg, need)
    validate_ranging(p.ranging, a.signal, origin)
    need(
        0 <= p.preprocess.blind_zone_samples < a.n_samples,
        f"preprocess.blind_zone_samples must be in [0, {a.n_samples})",
    )
    d = p.detect
    need(d.threshold > 0, f"detect.threshold must be > 0, got {d.threshold}")
    check_range("detect.hysteresis", d.hysteresis, origin)
    need(d.min_amplitude >= 0, f"detect.min_amplitude must be >= 0, got {d.min_amplitude}")
    check_range("detect.max_echoes", d.max_echoes, origin)
    m = p.memg
    check_range("memg.max_iterations", m.max_iterations, origin)
    check_range("memg.mu_window", m.mu_window, origin)
    check_range("memg.split_min_sigma", m.split_min_sigma, origin)
    check_range("memg.split_max_cost_ratio", m.split_max_cost_ratio, origin)
    need(m.toa in TOA_METHODS, f"memg.toa must be one of {TOA_METHODS}, got {m.toa!r}")
    s = p.associate
    need(
        s.method in ASSOCIATION_METHODS,
        f"associate.method must be one of {ASSOCIATION_METHODS}, got {s.method!r}",
    )
    need(
        n_listen < 3 or 3 <= s.min_channels <= n_listen,
        f"associate.min_channels must be in [3, {n_listen}], got {s.min_channels}",
    )
    need(
        s.tolerance_mm >= 0 and s.max_residual_mm > 0,
        "associate.tolerance_mm must be >= 0 and max_residual_mm > 0",
    )
    loc = p.locate
    need(
        0 < loc.toa_sigma_samples <= 100,
        f"locate.toa_sigma_samples must be in (0, 100], got {loc.toa_sigma_samples}",
    )
    need(
        loc.toa_sigma_per_background >= 0 and loc.toa_sigma_alpha_counts >= 0,
        "locate.toa_sigma_per_background and locate.toa_sigma_alpha_counts must be >= 0",
    )
    need(
        abs(loc.toa_shift_background_after) <= 5 and abs(loc.toa_shift_background_before) <= 5,
        "locate.toa_shift_background_after/before must be in [-5, 5] samples",
    )
    _validate_scene(p.scene, origin)
    _validate_echo_timing(p.echo_timing, g.n_channels, need, origin)
    validate_track(p.track, origin)
    validate_frame(p.frame, origin)


def _validate_window(m, need) -> None:
    need(
        1 <= m.window_before <= 64 and 1 <= m.window_after <= 64,
        f"memg.window_before and memg.window_after must be in [1, 64], got "
        f"{m.window_before} and {m.window_after}",
    )


def _validate_scene(sc: SceneSpec, origin: str) -> None:
    if sc.selection not in SCENE_SELECTIONS:
        raise ConfigError(
            f"{origin}: scene.selection must be one of {SCENE_SELECTIONS}, got {sc.selection!r}"
        )
    for f in dataclasses.fields(SceneSpec):
        if f.name not in ("static_model", "selection", "keep_best", "error_model"):
            check_range(f"scene.{f.name}", getattr(sc, f.name), origin)
    m = sc.error_model
    if m and not (len(m) == 8 and all(abs(v) <= 100 for v in m) and m[6] > 0 and m[7] > 0):
        raise ConfigError(
            f"{origin}: scene.error_model must be empty or 8 numbers in [-100, 100] "
            f"(the last two > 0), got {list(m)}"
        )


def _validate_echo_timing(e: EchoTimingSpec, n_channels: int, need, origin: str) -> None:
    need(
        e.estimator in ECHO_TIMING_ESTIMATORS,
        f"echo_timing.estimator must be one of {ECHO_TIMING_ESTIMATORS}, got {e.estimator!r}",
    )
    check_range("echo_timing.half_window", e.half_window, origin)
    need(
        e.toa_correction in TOA_CORRECTIONS,
        f"echo_timing.toa_correction must be one of {TOA_CORRECTIONS}, got {e.toa_correction!r}",
    )
    shifts = e.delay_shift_samples
    need(
        len(shifts) in (0, n_channels) and all(abs(v) <= 5 for v in shifts),
        f"echo_timing.delay_shift_samples must be empty or {n_channels} values in [-5, 5]",
    )


def profile_to_dict(p: Profile) -> dict[str, Any]:
    """The profile as TOML-ready nested dicts (arrays as lists)."""
    g = p.geometry
    geometry: dict[str, Any] = {
        "speed_of_sound_m_s": g.speed_of_sound_m_s,
        "emitter_mm": g.emitter_mm.tolist(),
        "facing": g.facing.tolist(),
        "channels_mm": g.channels_mm.tolist(),
        "listening": g.listening_mask().tolist(),
        "delay_samples": g.delays().tolist(),
    }
    out: dict[str, Any] = {"name": p.name, "description": p.description, "geometry": geometry}
    for key in SECTIONS:
        out[key] = dataclasses.asdict(getattr(p, key))
    return out


def dump_toml(data: dict[str, Any]) -> str:
    """A minimal TOML writer for profile-shaped data (tables of scalars and lists)."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for key, table in data.items():
        if isinstance(table, dict):
            lines.append(f"\n[{key}]")
            lines.extend(f"{k} = {_toml_value(v)}" for k, v in table.items())
    return "\n".join(lines) + "\n"


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(float(v)) if isinstance(v, float) else str(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")
