"""Sinks, MultiSink fan-out and open_outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spiel_edge.errors import ConfigError
from spiel_edge.outputs import MultiSink, open_outputs, recording_path
from spiel_edge.outputs.ndjson import NdjsonSink
from spiel_edge.outputs.sink import ACQUISITIONS, Sink
from spiel_edge.outputs.udp import UdpSink
from spiel_edge.recordings.mcap_writer import McapSink


class Collect(Sink):
    capabilities = frozenset({ACQUISITIONS})

    def __init__(self, fail_with: Exception | None = None):
        self.records, self.acquisitions, self.closed, self.fail_with = [], [], 0, fail_with

    def write(self, record):
        if self.fail_with:
            raise self.fail_with
        self.records.append(record)

    def write_acquisition(self, acq, frames):
        if self.fail_with:
            raise self.fail_with
        self.acquisitions.append((acq, frames))

    def close(self):
        self.closed += 1


class RecordsOnly(Sink):  # the other hooks: Sink's no-ops
    def __init__(self):
        self.records = []

    def write(self, record):
        self.records.append(record)


def test_multisink_fans_out_and_drops_a_failing_sink():
    good, bad, plain = Collect(), Collect(OSError("disk full")), RecordsOnly()
    sink = MultiSink([good, bad, plain])
    frames = np.zeros((4, 64))
    sink.write_acquisition({"seq": 0}, frames)
    sink.write({"seq": 0})
    sink.write({"seq": 1})
    assert [r["seq"] for r in good.records] == [0, 1] == [r["seq"] for r in plain.records]
    assert good.acquisitions[0][1] is frames
    assert bad not in sink.sinks and bad.closed == 1  # dropped and closed at the first failure
    assert sink.wants_acquisitions and sink.alive
    sink.close()
    assert good.closed == 1
    assert not MultiSink([RecordsOnly()]).wants_acquisitions


def test_ndjson_file_one_line_per_record(tmp_path):
    path = tmp_path / "out.ndjson"
    sink = NdjsonSink(path)
    sink.write({"position_mm": [1.0, 2.0, 3.0]})
    sink.write({"position_mm": None})
    sink.close()
    lines = path.read_text().splitlines()
    assert [json.loads(line)["position_mm"] for line in lines] == [[1.0, 2.0, 3.0], None]


def test_open_outputs_several_at_once(tmp_path):
    ndjson, mcap = tmp_path / "a.ndjson", tmp_path / "r.mcap"
    outputs = open_outputs(output=str(ndjson), record=mcap, udp=["127.0.0.1:9", "localhost:9"])
    kinds = [type(s) for s in outputs.sinks]
    assert kinds == [NdjsonSink, McapSink, UdpSink, UdpSink]
    outputs.write_acquisition({"seq": 0}, np.ones((4, 64)))
    outputs.write({"seq": 0, "position_mm": None})
    outputs.close()
    assert ndjson.read_text().count("\n") == 1
    assert (
        mcap.stat().st_size > 0 and mcap.read_bytes()[-8:] == b"\x89MCAP0\r\n"
    )  # footer magic: finalized


def test_open_outputs_none_means_no_ndjson():
    assert open_outputs(output=None).sinks == []


def test_open_outputs_closes_what_it_opened_on_failure(tmp_path):
    mcap = tmp_path / "r.mcap"
    with pytest.raises(ConfigError, match="--udp"):
        open_outputs(output=None, record=mcap, udp="no-port-here")
    assert mcap.read_bytes()[-8:] == b"\x89MCAP0\r\n"


def test_recording_path_expands_time_and_checks(tmp_path):
    stamp = 1_700_000_000  # 2023-11-14 in every time zone
    path = recording_path(tmp_path / "spiel-%Y%m%d.mcap", now=stamp)
    assert path.name.startswith("spiel-202311") and path.suffix == ".mcap"
    with pytest.raises(ConfigError, match="must end in .mcap"):
        recording_path(tmp_path / "x.bag")
    with pytest.raises(ConfigError, match="does not exist"):
        recording_path(tmp_path / "missing" / "x.mcap")


def test_unknown_extras_fail_with_install_hint(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_extras(name, *args, **kwargs):
        if name in ("foxglove", "zenoh"):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_extras)
    with pytest.raises(ConfigError, match=r"pip install 'spiel-edge\[foxglove\]'"):
        open_outputs(output=None, foxglove="0")
    with pytest.raises(ConfigError, match=r"pip install 'spiel-edge\[zenoh\]'"):
        open_outputs(output=None, zenoh="robots/r1/spiel")
