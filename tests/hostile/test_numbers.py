"""Numbers that are numbers (issue 28, part 4): every number of a profile, calibration or board
config is finite and within a documented range, checked once at load with a message naming
the key. Found by introspection: a field added later is covered without a new test."""

from __future__ import annotations

import dataclasses
import math

import pytest

from spiel_edge.errors import ConfigError
from spiel_edge.profile.schema import SECTIONS, load_profile, profile_from_dict, profile_to_dict

BASE = profile_to_dict(load_profile("spiel-icra23"))


def _numeric_keys() -> list[tuple[str, str, type]]:
    keys = []
    for section, cls in SECTIONS.items():
        for field in dataclasses.fields(cls):
            value = getattr(cls(), field.name)
            if isinstance(value, bool) or field.name == "static_model":
                continue
            if isinstance(value, (int, float, tuple)):
                keys.append((section, field.name, type(value)))
    return keys


NUMERIC = _numeric_keys()
FLOAT_BAD = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf, "1e308": 1e308}
INT_BAD = {"1e12": 10**12, "-1e12": -(10**12)}


def _cases():
    for section, name, kind in NUMERIC:
        bad = INT_BAD if kind is int else FLOAT_BAD
        for label, value in bad.items():
            yield pytest.param(section, name, kind, value, id=f"{section}.{name}={label}")


def _with(section: str, name: str, kind: type, value) -> dict:
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in BASE.items()}
    if kind is tuple:
        current = data[section][name]
        value = [value] * max(len(current), 3 if name != "rotation_xyzw" else 4)
    data[section][name] = value
    return data


@pytest.mark.parametrize(("section", "name", "kind", "value"), list(_cases()))
def test_every_profile_number_is_finite_and_in_range(section, name, kind, value):
    with pytest.raises(ConfigError) as info:
        profile_from_dict(_with(section, name, kind, value), origin="p.toml")
    message = str(info.value)
    assert f"{section}.{name}" in message, message  # the key is named
    assert "\n" not in message


def test_the_table_covers_every_numeric_field():
    assert len(NUMERIC) >= 40  # the introspection found the sections' numbers


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("speed_of_sound_m_s", math.nan),
        ("speed_of_sound_m_s", math.inf),
        ("emitter_mm", [math.nan, 0.0, 0.0]),
        ("facing", [0.0, math.inf, 1.0]),
        ("delay_samples", [math.nan, 0.0, 0.0, 0.0]),
        ("channels_mm", [[math.inf, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]]),
    ],
    ids=lambda v: v if isinstance(v, str) else "",
)
def test_geometry_numbers_are_finite(key, value):
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in BASE.items()}
    data["geometry"][key] = value
    with pytest.raises(ConfigError, match=f"geometry.{key}"):
        profile_from_dict(data, origin="cal.toml")


@pytest.mark.parametrize(
    "line",
    [
        "[associate]\nmissing_penalty_mm = nan",
        "[associate]\nrange_weight = inf",
        "[detect]\nthreshold = inf",
        "[detect]\nmin_amplitude = 1e308",
        "[locate]\ntoa_sigma_per_background = inf",
        "[locate]\ntoa_sigma_alpha_counts = -inf",
        "[scene]\nmissing_penalty_mm = nan",
        "[geometry]\nspeed_of_sound_m_s = nan",
    ],
    ids=lambda v: v.replace("\n", " "),
)
def test_a_calibration_with_a_non_number_is_refused_by_the_cli(cli, csv_folder, tmp_path, line):
    cal = tmp_path / "cal.toml"
    cal.write_text(line + "\n")
    ran = cli("replay", csv_folder[0], "--calibration", cal, "-o", tmp_path / "o.ndjson")
    key = line.split("]")[0][1:] + "." + line.split("\n")[1].split(" =")[0]
    assert ran.status == 2 and key in ran.err, ran
    assert not (tmp_path / "o.ndjson").exists()


BOARD_KEYS = ["sample_rate_hz", "carrier_hz", "gain_db", "acquisition_rate_hz"]


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 1e308], ids=str)
@pytest.mark.parametrize("key", BOARD_KEYS)
def test_board_config_floats_are_finite_and_in_range(key, value):
    from spiel_edge.board_config import schema

    config = schema.from_profile(load_profile("spiel-icra23"))
    config["acquisition"][key] = value
    with pytest.raises(ConfigError, match=f"acquisition.{key}"):
        schema.validate(config)


@pytest.mark.parametrize("value", [math.nan, math.inf, -1.0, 1e9], ids=str)
def test_board_calibration_residual_is_bounded(value):
    from spiel_edge.board_config import schema

    config = schema.from_profile(load_profile("spiel-icra23"))
    config["calibration"] = {"residual_samples": value}
    with pytest.raises(ConfigError, match="calibration.residual_samples"):
        schema.validate(config)
