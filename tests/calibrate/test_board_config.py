"""Board config schema, blob, and push/commit/pull on a two-slot flash with power cuts."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from spiel_edge.board_config import profile_choice
from spiel_edge.board_config import schema as bc
from spiel_edge.board_config.flash import commit, pull, push
from spiel_edge.errors import ConfigError, DeviceError
from spiel_edge.profile.schema import load_profile
from spiel_edge.protocol.errors import ErrorCode
from tests.calibrate.fake_board import (
    DeviceDisconnectedError,
    DeviceRequestError,
    FakeBoardSession,
    TwoSlotFlash,
)


@pytest.fixture
def config():
    return bc.from_profile(load_profile(), "proto-1")


def test_blob_round_trip_and_header(config):
    blob = bc.encode(config)
    assert blob[:4] == bc.MAGIC
    assert bc.decode(blob) == config
    fields = bc.HEADER.unpack_from(blob)
    assert (
        fields[3] == config["acquisition"]["n_samples"] and fields[-1] == len(blob) - bc.HEADER.size
    )


@pytest.mark.parametrize(
    "change, message",
    [
        ({"acquisition": {"gain_db": 75.0}}, r"acquisition.gain_db must be float in \[0, 60\]"),
        ({"acquisition": {"n_samples": "64"}}, r"acquisition.n_samples must be int in \[8, 4096\]"),
        (
            {"acquisition": {"n_samples": 8}},
            r"blind_zone_samples must be in \[0, n_samples - 1 = 7\]",
        ),
        (
            {"acquisition": {"decimation": 255, "sample_rate_hz": 50000.0}},
            r"decimation must be in \[1, 200\]",
        ),
        ({"acquisition": {"pulse_cycles": 200}}, r"pulse_cycles must be in \[1, 71\]"),
        (
            {"acquisition": {"acquisition_rate_hz": 400.0}},
            r"acquisition_rate_hz must be in \[0.1, 343.8\]",
        ),
        ({"acquisition": {"volume": 3}}, r"unknown key\(s\) \['volume'\] in \[acquisition\]"),
        ({"board": {"name": "x" * 40}}, r"board.name must be 1-32"),
        (
            {"geometry": {"speed_of_sound_m_s": 5000.0}},
            r"speed_of_sound_m_s must be a number in \[200, 2000\]",
        ),
        ({"geometry": {"listening": [False, False, False, False]}}, "at least 1 listening"),
        (
            {"calibration": {"residual_samples": -1.0}},
            r"calibration.residual_samples must be in \[0, 100\]",
        ),
        ({"wifi": {}}, r"unknown table\(s\) \['wifi'\]"),
    ],
)
def test_validation_names_key_and_range(config, change, message):
    with pytest.raises(ConfigError, match=message):
        bc.overlay(config, change)


def test_missing_key_and_corrupt_blob(config):
    broken = copy.deepcopy(config)
    del broken["acquisition"]["gain_db"]
    with pytest.raises(
        ConfigError, match=r"acquisition.gain_db is required \(float in \[0, 60\]\)"
    ):
        bc.validate(broken)
    blob = bytearray(bc.encode(config))
    blob[10] ^= 0x01  # the header's n_samples no longer matches the TOML
    with pytest.raises(ConfigError, match="disagree|must be"):
        bc.decode(bytes(blob))
    with pytest.raises(ConfigError, match="not a spiel-edge config"):
        bc.decode(b"XXXX" + bytes(blob[4:]))


def test_calibration_overlay_and_diff(config):
    partial = {"geometry": {"delay_samples": [1.0, 1.1, 1.2, 1.3], "speed_of_sound_m_s": 340}}
    new = bc.overlay(config, partial)
    assert new["geometry"]["speed_of_sound_m_s"] == 340.0
    lines = bc.diff(config, new)
    assert len(lines) == 2 and all(line.startswith("~ geometry.") for line in lines)
    assert bc.diff(config, config) == []
    assert all(line.startswith("+ ") for line in bc.diff(None, config))


def test_profile_from_board_uses_the_stored_geometry(config):
    session = FakeBoardSession(TwoSlotFlash())
    base = load_profile()
    assert profile_choice.profile_from_board(session, base) is base  # nothing stored yet
    moved = bc.overlay(
        config,
        {
            "geometry": {"channels_mm": [[0, 0, 0], [-40, -60, 0], [70, 0, 0], [-40, 60, 0]]},
            "acquisition": {"blind_zone_samples": 7},
        },
    )
    commit(session, push(session, moved))
    profile = profile_choice.profile_from_board(session, base)
    assert np.array_equal(profile.geometry.channels_mm[2], [70, 0, 0])
    assert profile.preprocess.blind_zone_samples == 7
    assert profile.detect == base.detect


@pytest.mark.parametrize("code, kept", [(ErrorCode.UNSUPPORTED, True), (ErrorCode.BUSY, False)])
def test_profile_from_board_when_the_board_cannot_store_a_config(code, kept):
    session = FakeBoardSession(TwoSlotFlash())

    def refuse(source=0):
        raise DeviceRequestError("refused", code=code)

    session.read_config = refuse
    base = load_profile()
    if kept:  # a board without config support runs with the profile
        assert profile_choice.profile_from_board(session, base) is base
    else:  # anything else is the board's trouble, not a missing config
        with pytest.raises(DeviceError, match="refused"):
            profile_choice.profile_from_board(session, base)


def test_run_profile_precedence(config, tmp_path):
    session = FakeBoardSession(TwoSlotFlash())
    moved = bc.overlay(config, {"geometry": {"speed_of_sound_m_s": 350.0}})
    commit(session, push(session, moved))
    profile, source = profile_choice.run_profile(session, "spiel-icra23")
    assert profile.geometry.speed_of_sound_m_s == 350.0 and source == "board 'proto-1'"
    profile, source = profile_choice.run_profile(session, "spiel-icra23", use_board=False)
    assert profile.geometry.speed_of_sound_m_s == 343.0 and source == "profile 'spiel-icra23'"
    cal = tmp_path / "cal.toml"
    cal.write_text("[geometry]\nspeed_of_sound_m_s = 340.0\n")
    profile, source = profile_choice.run_profile(session, "spiel-icra23", cal)
    assert (
        profile.geometry.speed_of_sound_m_s == 340.0
        and source.startswith("calibration")
        and source.endswith("over board 'proto-1'")
    )


def test_push_commit_pull_round_trip(config):
    session = FakeBoardSession(TwoSlotFlash())
    assert pull(session) is None
    sizes = []
    crc = push(session, config, progress=sizes.append)
    assert sum(sizes) == len(bc.encode(config))
    assert pull(session) is None  # staged only
    assert pull(session, staging=True) == config
    assert commit(session, crc) == crc
    assert pull(session) == config


def test_push_detects_a_bad_read_back(config):
    session = FakeBoardSession(TwoSlotFlash())
    write = session.write_config
    session.write_config = lambda blob, progress=None: write(blob[:-1] + b"!", progress)
    with pytest.raises(DeviceError, match="differs"):
        push(session, config)


def test_commit_refuses_staged_junk():
    session = FakeBoardSession(TwoSlotFlash())
    session.staging = b"garbage that is not a config"
    with pytest.raises(ConfigError):
        commit(session)


def test_power_cut_at_every_flash_operation_keeps_the_old_config(config):
    new = bc.overlay(config, {"board": {"name": "proto-2"}, "acquisition": {"gain_db": 30.0}})
    probe = TwoSlotFlash()
    s = FakeBoardSession(probe)
    commit(s, push(s, config))
    before = probe.ops
    commit(s, push(s, new))
    ops_per_commit = probe.ops - before
    assert ops_per_commit >= 3  # erase, at least one page, header
    for cut in range(ops_per_commit):
        flash = TwoSlotFlash()
        s = FakeBoardSession(flash)
        commit(s, push(s, config))
        flash.cut_at = flash.ops + cut
        with pytest.raises(DeviceDisconnectedError):
            commit(s, push(s, new))
        rebooted = FakeBoardSession(flash)  # RAM staging lost, flash kept
        assert pull(rebooted) == config, f"cut at operation {cut}"
        commit(rebooted, push(rebooted, new))  # and the next commit works
        assert pull(rebooted) == new
