"""The board's own config: acquisition settings plus the calibrated geometry, stored in its flash.

A board config is a TOML document with the tables ``[board]`` (name), ``[acquisition]``
(sample count, rate and decimation, carrier and pulse length, gain, blind zone, acquisition
rate), ``[geometry]`` (as in a device profile: any host that reads the board knows where its
transducers are) and an optional ``[calibration]`` (where the geometry came from). Validation
checks types, ranges and cross-field rules and names the key and the allowed range.

The blob written to the board is a fixed little-endian header the firmware reads without a
TOML parser (magic, version, the acquisition scalars) followed by the whole config as UTF-8
TOML for hosts. Decoding checks that both agree. Pure, except the file helpers and, at the
end, the profile a host runs with: ``profile_choice.run_profile`` (``--calibration`` > the board's stored
config > the profile), whose board read goes through a device session.
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path
from typing import Any

from spiel_edge.compat import tomllib
from spiel_edge.errors import ConfigError
from spiel_edge.profile.ranges import RANGES
from spiel_edge.profile.schema import (
    Profile,
    dump_toml,
    profile_from_dict,
    profile_to_dict,
)
from spiel_edge.protocol.config_blob import (
    HEADER,
    HEADER_SIZE,
    MAGIC,
    VERSION,
    pack_header,
    unpack_header,
)
from spiel_edge.safety.guard import read_config_text, shorten
from spiel_edge.safety.limits import loads_toml

__all__ = [
    "ACQUISITION",
    "CALIBRATION",
    "HEADER",
    "MAGIC",
    "MAX_ADC_HZ",
    "NAME_MAX",
    "TABLES",
    "VERSION",
    "decode",
    "diff",
    "encode",
    "from_profile",
    "overlay",
    "profile_with_board",
    "read_file",
    "to_toml",
    "validate",
]

log = logging.getLogger(__name__)

# The blob's header layout (MAGIC, VERSION, HEADER) is the protocol's: spiel_edge.protocol.config_blob
MAX_ADC_HZ = 10e6  # the ADC's maximum rate: sample_rate_hz * decimation may not exceed it
NAME_MAX = 32

# key -> (type, low, high); ranges are inclusive
ACQUISITION = {
    "n_samples": (int, *RANGES["acquisition.n_samples"]),
    "sample_rate_hz": (float, *RANGES["acquisition.sample_rate_hz"]),
    "decimation": (int, 1, 256),
    "carrier_hz": (float, 20e3, 5e6),
    "pulse_cycles": (int, 1, 1000),
    "gain_db": (float, 0.0, 60.0),
    "blind_zone_samples": (int, 0, 4095),
    "acquisition_rate_hz": (float, 0.1, 1000.0),
}
CALIBRATION = {"source": str, "date": str, "residual_samples": float}
TABLES = ("board", "acquisition", "geometry", "calibration")


def validate(data: dict[str, Any], origin: str = "board config") -> dict[str, Any]:
    """The config normalised (ints as floats where floats are due, geometry canonical), or
    ConfigError naming the key and the allowed range."""
    _need(isinstance(data, dict), origin, "must be a TOML table")
    unknown = set(data) - set(TABLES)
    _need(not unknown, origin, f"unknown table(s) {sorted(unknown)}; allowed: {list(TABLES)}")
    for table in ("board", "acquisition", "geometry"):
        _need(isinstance(data.get(table), dict), origin, f"[{table}] table is required")
    out: dict[str, Any] = {
        "board": _board(data["board"], origin),
        "acquisition": _acquisition(data["acquisition"], origin),
    }
    out["geometry"] = _geometry(data["geometry"], out["acquisition"], origin)
    if "calibration" in data:
        out["calibration"] = _calibration(data["calibration"], origin)
    return out


def _need(ok: bool, origin: str, message: str) -> None:
    if not ok:
        raise ConfigError(f"{origin}: {message}")


def _board(table: dict, origin: str) -> dict:
    unknown = set(table) - {"name"}
    _need(not unknown, origin, f"unknown key(s) {sorted(unknown)} in [board]; allowed: ['name']")
    name = table.get("name")
    ok = (
        isinstance(name, str)
        and 1 <= len(name) <= NAME_MAX
        and name.isascii()
        and name.isprintable()
    )
    _need(ok, origin, f"board.name must be 1-{NAME_MAX} printable ASCII characters, got {name!r}")
    return {"name": name}


def _acquisition(table: dict, origin: str) -> dict:
    unknown = set(table) - set(ACQUISITION)
    _need(
        not unknown,
        origin,
        f"unknown key(s) {sorted(unknown)} in [acquisition]; allowed: {sorted(ACQUISITION)}",
    )
    out = {}
    for key, (kind, lo, hi) in ACQUISITION.items():
        _need(
            key in table,
            origin,
            f"acquisition.{key} is required ({kind.__name__} in [{lo:g}, {hi:g}])",
        )
        value = table[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        ok = isinstance(value, kind) and not isinstance(value, bool) and lo <= value <= hi
        _need(
            ok,
            origin,
            f"acquisition.{key} must be {kind.__name__} in [{lo:g}, {hi:g}], got {table[key]!r}",
        )
        out[key] = value
    _cross_rules(out, origin)
    return out


def _cross_rules(a: dict, origin: str) -> None:
    n, rate = a["n_samples"], a["sample_rate_hz"]
    _need(
        float(rate).is_integer(),
        origin,
        f"acquisition.sample_rate_hz must be a whole number of Hz (the stream carries it as an "
        f"integer), got {rate!r}",
    )
    _need(
        a["blind_zone_samples"] < n,
        origin,
        f"acquisition.blind_zone_samples must be in [0, n_samples - 1 = {n - 1}], got {a['blind_zone_samples']}",
    )
    _need(
        rate * a["decimation"] <= MAX_ADC_HZ,
        origin,
        f"acquisition.decimation must be in [1, {int(MAX_ADC_HZ // rate)}] at sample_rate_hz = {rate:g} "
        f"(the ADC runs at most {MAX_ADC_HZ:g} Hz), got {a['decimation']}",
    )
    pulse_samples = a["pulse_cycles"] / a["carrier_hz"] * rate
    max_cycles = int(max(a["blind_zone_samples"], 1) * a["carrier_hz"] / rate)
    _need(
        pulse_samples <= max(a["blind_zone_samples"], 1),
        origin,
        f"acquisition.pulse_cycles must be in [1, {max_cycles}] so that the pulse ends inside the blind zone "
        f"({a['blind_zone_samples']} samples), got {a['pulse_cycles']}",
    )
    max_rate = rate / n
    _need(
        a["acquisition_rate_hz"] <= max_rate,
        origin,
        f"acquisition.acquisition_rate_hz must be in [0.1, {max_rate:.4g}] for {n} samples at {rate:g} Hz, "
        f"got {a['acquisition_rate_hz']:g}",
    )


def _geometry(table: dict, acq: dict, origin: str) -> dict:
    """Validated by the profile's own rules (shapes, >= 1 listening channel, speed range)."""
    profile = profile_from_dict(
        {
            "name": "board",
            "geometry": table,
            "acquisition": {"n_samples": acq["n_samples"], "sample_rate_hz": acq["sample_rate_hz"]},
        },
        origin=origin,
    )
    full = profile_to_dict(profile)["geometry"]
    return {key: full[key] for key in full if key in table or key == "channels_mm"}


def _calibration(table: Any, origin: str) -> dict:
    _need(isinstance(table, dict), origin, "[calibration] must be a table")
    unknown = set(table) - set(CALIBRATION)
    _need(
        not unknown,
        origin,
        f"unknown key(s) {sorted(unknown)} in [calibration]; allowed: {sorted(CALIBRATION)}",
    )
    out = {}
    for key, value in table.items():
        kind = CALIBRATION[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        _need(
            isinstance(value, kind) and not isinstance(value, bool),
            origin,
            f"calibration.{key} must be {kind.__name__}, got {value!r}",
        )
        _need(
            kind is not float or 0.0 <= value <= 100.0,
            origin,
            f"calibration.{key} must be in [0, 100], got {value!r}",
        )
        out[key] = value
    return out


def overlay(
    base: dict[str, Any], partial: dict[str, Any], origin: str = "board config"
) -> dict[str, Any]:
    """``partial`` (e.g. a calibration file with only [geometry]) over ``base``, validated."""
    _need(isinstance(partial, dict), origin, "must be a TOML table")
    unknown = set(partial) - set(TABLES)
    _need(not unknown, origin, f"unknown table(s) {sorted(unknown)}; allowed: {list(TABLES)}")
    merged = copy.deepcopy(base)
    for table, values in partial.items():
        _need(isinstance(values, dict), origin, f"[{table}] must be a table")
        merged.setdefault(table, {}).update(values)
    return validate(merged, origin)


def from_profile(profile: Profile, name: str = "spiel-board", **acquisition: Any) -> dict[str, Any]:
    """A board config with a profile's geometry and acquisition (other settings: defaults)."""
    a = profile.acquisition
    defaults = {
        "n_samples": a.n_samples,
        "sample_rate_hz": a.sample_rate_hz,
        "decimation": 8,
        "carrier_hz": a.carrier_hz,
        "pulse_cycles": 30,
        "gain_db": 20.0,
        "blind_zone_samples": profile.preprocess.blind_zone_samples,
        "acquisition_rate_hz": 30.0,
    }
    geometry = profile_to_dict(profile)["geometry"]
    return validate(
        {"board": {"name": name}, "acquisition": {**defaults, **acquisition}, "geometry": geometry}
    )


def to_toml(config: dict[str, Any]) -> str:
    return dump_toml({table: config[table] for table in TABLES if table in config})


def encode(config: dict[str, Any]) -> bytes:
    """The bytes for the board: the firmware header, then the config as UTF-8 TOML."""
    config = validate(config)
    text = to_toml(config).encode("utf-8")
    return pack_header(config["acquisition"], len(text)) + text


def decode(blob: bytes, origin: str = "board") -> dict[str, Any]:
    """The validated config from a blob read from the board; ConfigError if it is not one."""
    _need(
        len(blob) >= HEADER_SIZE,
        origin,
        f"config is {len(blob)} bytes, shorter than its {HEADER_SIZE}-byte header",
    )
    header = unpack_header(blob)
    magic, version = header.magic, header.version
    size, length = header.header_size, header.toml_length
    _need(
        magic == MAGIC,
        origin,
        f"config does not start with {MAGIC!r} (got {magic!r}): not a spiel-edge config",
    )
    _need(
        version == VERSION and size == HEADER_SIZE,
        origin,
        f"config version {version} is not supported (this host reads {VERSION})",
    )
    _need(
        len(blob) == size + length,
        origin,
        f"config length {len(blob)} does not match its header ({size} + {length})",
    )
    try:
        data = tomllib.loads(blob[size:].decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{origin}: stored config is not valid TOML: {exc}") from exc
    except RecursionError:
        raise ConfigError(f"{origin}: stored config is not valid TOML: nested too deeply") from None
    config = validate(data, origin)
    stored = pack_header(config["acquisition"], length)
    _need(
        stored == blob[:size],
        origin,
        "config header and TOML disagree: the stored config is corrupt",
    )
    return config


def read_file(path: str | Path) -> dict[str, Any]:
    """A TOML file as a dict (full board config or a partial one such as a calibration)."""
    path = Path(path)
    return loads_toml(read_config_text(path, "config"), ConfigError, shorten(path))


def diff(old: dict[str, Any] | None, new: dict[str, Any]) -> list[str]:
    """What would change, one ``table.key: old -> new`` line per changed key."""
    before, after = _flatten(old or {}), _flatten(new)
    lines = []
    for key in sorted(set(before) | set(after)):
        if key not in after:
            lines.append(f"- {key} = {before[key]!r}")
        elif key not in before:
            lines.append(f"+ {key} = {after[key]!r}")
        elif before[key] != after[key]:
            lines.append(f"~ {key}: {before[key]!r} -> {after[key]!r}")
    return lines


def _flatten(config: dict[str, Any]) -> dict[str, Any]:
    return {
        f"{t}.{k}": v
        for t, table in config.items()
        if isinstance(table, dict)
        for k, v in table.items()
    }


def profile_with_board(base: Profile, config: dict[str, Any]) -> Profile:
    """``base`` with the board's geometry, sample count, rates and blind zone."""
    merged = profile_to_dict(base)
    a = config["acquisition"]
    merged["geometry"].update(config["geometry"])
    merged["acquisition"].update(
        n_samples=a["n_samples"], sample_rate_hz=a["sample_rate_hz"], carrier_hz=a["carrier_hz"]
    )
    merged["preprocess"]["blind_zone_samples"] = a["blind_zone_samples"]
    return profile_from_dict(merged, origin=f"board {config['board']['name']!r}")
