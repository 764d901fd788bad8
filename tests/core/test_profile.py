import numpy as np
import pytest

from spiel_edge.errors import ConfigError
from spiel_edge.profile.schema import (
    apply_calibration,
    builtin_profiles,
    dump_toml,
    load_profile,
    profile_from_dict,
    profile_to_dict,
)


def test_builtin_profile_matches_the_prototype(profile):
    assert "spiel-icra23" in builtin_profiles()
    g = profile.geometry
    assert g.n_channels == 4 and profile.acquisition.n_samples == 64
    np.testing.assert_allclose(np.linalg.norm(g.channels_mm[1:], axis=1), 75.0, atol=0.01)
    assert profile.mm_per_sample == pytest.approx(343000 / 22000)
    assert profile.preprocess.blind_zone_samples == 9


def test_round_trip_through_toml(tmp_path, profile):
    path = tmp_path / "copy.toml"
    path.write_text(dump_toml(profile_to_dict(profile)))
    again = load_profile(path)
    assert profile_to_dict(again) == profile_to_dict(profile)


def test_other_hardware_any_receivers(tmp_path, profile):
    data = profile_to_dict(profile)
    data["geometry"]["channels_mm"] = [
        [0, 0, 0],
        [50, 0, 0],
        [0, 50, 0],
        [-50, 0, 0],
        [0, -50, 0],
        [35, 35, 5],
    ]
    data["geometry"]["listening"] = [False, True, True, True, True, True]
    data["geometry"]["delay_samples"] = [0.0] * 6
    data["echo_timing"]["delay_shift_samples"] = []  # per channel, like the delays
    data["acquisition"]["n_samples"] = 512
    p = profile_from_dict(data)
    assert p.geometry.n_channels == 6 and int(p.geometry.listening_mask().sum()) == 5


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d["detect"].update(threshold=-1.0), "detect.threshold"),
        (lambda d: d["memg"].update(toa="median"), "memg.toa"),
        (lambda d: d["memg"].update(split_min_sigma=0.1), "memg.split_min_sigma"),
        (lambda d: d["memg"].update(split_max_cost_ratio=1.5), "memg.split_max_cost_ratio"),
        (lambda d: d["memg"].update(split_merged="yes"), "memg.split_merged"),
        (
            lambda d: d["geometry"].update(listening=[False, False, False, False]),
            "at least 1 listening",
        ),
        (lambda d: d["geometry"].update(channels_mm=[[0, 0]]), "geometry.channels_mm"),
        (lambda d: d["geometry"].update(delay_samples=[1.0]), "geometry.delay_samples"),
        (lambda d: d["geometry"].update(speed_of_sound_m_s=5.0), "speed_of_sound"),
        (lambda d: d["acquisition"].update(n_samples="64"), "acquisition.n_samples must be int"),
        (lambda d: d["detect"].update(colour="red"), "unknown key"),
        (lambda d: d.update(extra={}), "unknown key"),
    ],
)
def test_invalid_profiles_name_the_key(profile, mutate, message):
    data = profile_to_dict(profile)
    mutate(data)
    with pytest.raises(ConfigError, match=message):
        profile_from_dict(data)


def test_errors_for_files(tmp_path, profile):
    with pytest.raises(ConfigError, match="unknown profile"):
        load_profile("no-such-board")
    with pytest.raises(ConfigError, match="not found"):
        load_profile(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_profile(bad)
    with pytest.raises(ConfigError, match="not found"):
        apply_calibration(profile, tmp_path / "nope.toml")


def test_calibration_overlays_geometry_only(tmp_path, profile):
    cal = tmp_path / "cal.toml"
    cal.write_text("[geometry]\nspeed_of_sound_m_s = 346.0\ndelay_samples = [1.0, 2.0, 3.0, 4.0]\n")
    p = apply_calibration(profile, cal)
    assert p.geometry.speed_of_sound_m_s == 346.0
    assert p.geometry.delays().tolist() == [1.0, 2.0, 3.0, 4.0]
    np.testing.assert_array_equal(p.geometry.channels_mm, profile.geometry.channels_mm)
    assert p.detect == profile.detect


def test_profile_cli_prints_a_loadable_copy(tmp_path, capsys):
    from spiel_edge.cli import main

    assert main(["profile", "list"]) == 0
    assert "spiel-icra23" in capsys.readouterr().out
    assert main(["profile", "show", "spiel-icra23"]) == 0
    copy = tmp_path / "mine.toml"
    copy.write_text(capsys.readouterr().out)
    assert profile_to_dict(load_profile(copy)) == profile_to_dict(load_profile("spiel-icra23"))
    assert main(["profile", "show", "nope"]) == 2
