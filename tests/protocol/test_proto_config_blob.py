"""The config blob header codec (spiel_edge.protocol.config_blob), alone and as the board uses it."""

from __future__ import annotations

import pytest

from spiel_edge.board_config import schema as bc
from spiel_edge.profile.schema import load_profile
from spiel_edge.protocol import MessageError, config_blob

ACQ = {
    "n_samples": 4096,
    "decimation": 8,
    "pulse_cycles": 30,
    "blind_zone_samples": 100,
    "sample_rate_hz": 400000.0,
    "carrier_hz": 40000.0,
    "gain_db": 20.0,
    "acquisition_rate_hz": 30.0,
}


def test_layout_is_the_one_boards_already_store() -> None:
    assert config_blob.HEADER.format == "<4sHHHHHHffffI" and config_blob.HEADER_SIZE == 36
    assert config_blob.MAGIC == b"SPCF" and config_blob.VERSION == 1
    assert set(config_blob.ACQUISITION_KEYS) == set(bc.ACQUISITION)


def test_pack_unpack_round_trip() -> None:
    raw = config_blob.pack_header(ACQ, 1234)
    assert len(raw) == 36 and raw[:4] == b"SPCF"
    header = config_blob.unpack_header(raw + b"toml")
    assert (header.magic, header.version, header.header_size) == (b"SPCF", 1, 36)
    assert header.acquisition == ACQ and header.toml_length == 1234


def test_board_blob_starts_with_the_protocol_header() -> None:
    config = bc.from_profile(load_profile(), "proto-1")
    blob = bc.encode(config)
    header = config_blob.unpack_header(blob)
    assert header.toml_length == len(blob) - 36
    assert header.acquisition["n_samples"] == config["acquisition"]["n_samples"]
    assert blob[:36] == config_blob.pack_header(config["acquisition"], header.toml_length)


@pytest.mark.parametrize(
    "acquisition, message",
    [
        ({**ACQ, "n_samples": 70000}, "config blob header"),
        ({k: v for k, v in ACQ.items() if k != "gain_db"}, "missing acquisition value 'gain_db'"),
    ],
)
def test_pack_rejects_values_that_do_not_fit(acquisition: dict, message: str) -> None:
    with pytest.raises(MessageError, match=message):
        config_blob.pack_header(acquisition, 0)


def test_unpack_rejects_short_input() -> None:
    with pytest.raises(MessageError, match="shorter than its header"):
        config_blob.unpack_header(b"SPCF\x01\x00")
