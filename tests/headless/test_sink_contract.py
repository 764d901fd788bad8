"""One contract every output passes (outputs/sink.py): it writes a record, an acquisition when
it says ACQUISITIONS, holds its writes only when it says HOLD, finalizes its file only when it
says FILE, closes twice without harm, and a fan-out counts a failing output instead of raising.
A new Sink class must be added to SINKS here (test_every_sink_class_is_under_contract)."""

from __future__ import annotations

import socket

import numpy as np
import pytest

import spiel_edge.outputs.fanout as fanout
from spiel_edge.outputs import MultiSink
from spiel_edge.outputs.sink import ACQUISITIONS, CAPABILITIES, FILE, HOLD, Sink
from spiel_edge.recordings.mcap_writer import McapSink

RECORD = {
    "seq": 0,
    "position_mm": [10.0, -20.0, 300.0],
    "reason": None,
    "residual_mm": 0.5,
    "echoes": [[12.0]] * 4,
    "matched": [0, 0, 0, 0],
    "targets": [
        {
            "position_mm": [10.0, -20.0, 300.0],
            "covariance_mm2": [[40.0, 5.0, 0.0], [5.0, 30.0, 0.0], [0.0, 0.0, 90.0]],
            "residual_mm": 0.5,
            "matched": [0, 0, 0, 0],
            "score": 1.0,
        }
    ],
    "t_host": 1.0,
}
FRAMES = np.zeros((4, 64), dtype=np.uint16)
ACQUISITION = {"seq": 0, "t_host": 1.0, "background": None}


def _ndjson(tmp_path):
    from spiel_edge.outputs.ndjson import NdjsonSink

    return NdjsonSink(tmp_path / "out.ndjson"), tmp_path / "out.ndjson"


def _stdout(tmp_path):
    from spiel_edge.outputs.ndjson import NdjsonSink

    return NdjsonSink("-"), None


def _mcap(tmp_path):
    return McapSink(tmp_path / "rec.mcap"), tmp_path / "rec.mcap"


def _ros2_mcap(tmp_path):
    from spiel_edge.recordings.ros2_mcap import Ros2McapSink

    return Ros2McapSink(tmp_path / "ros2.mcap"), tmp_path / "ros2.mcap"


def _udp(tmp_path):
    from spiel_edge.outputs.udp import UdpSink

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))  # a free port; nothing need listen: a send is fire-and-forget
        port = s.getsockname()[1]
    return UdpSink(f"127.0.0.1:{port}"), None


def _foxglove(tmp_path):
    pytest.importorskip("foxglove", reason="extra 'foxglove' not installed")
    from spiel_edge.outputs.foxglove import FoxgloveSink

    return FoxgloveSink("0", receivers_mm=[[0, 0, 0], [75, 0, 0]]), None


def _zenoh(encoding):
    def make(tmp_path):
        pytest.importorskip("zenoh", reason="extra 'zenoh' not installed")
        from spiel_edge.outputs.ros2 import ZenohSettings

        settings = ZenohSettings(mode="peer", connect=())
        return fanout._zenoh_sink("contract/test", encoding, None, settings), None

    return make


def _fanout(tmp_path):
    sink, path = _ndjson(tmp_path)
    return MultiSink([sink, McapSink(tmp_path / "also.mcap")]), path


SINKS = {
    "NdjsonSink": _ndjson,
    "NdjsonSink-stdout": _stdout,
    "McapSink": _mcap,
    "Ros2McapSink": _ros2_mcap,
    "UdpSink": _udp,
    "FoxgloveSink": _foxglove,
    "ZenohSink": _zenoh("json"),
    "ZenohRos2Sink": _zenoh("cdr"),
    "RmwZenohSink": _zenoh("rmw_zenoh"),
    "MultiSink": _fanout,
}


def _classes(base):
    for sub in base.__subclasses__():
        yield sub
        yield from _classes(sub)


def test_every_sink_class_is_under_contract():
    import spiel_edge.outputs.foxglove  # noqa: F401  (each module that defines a sink)
    import spiel_edge.outputs.ndjson  # noqa: F401
    import spiel_edge.outputs.rmw_zenoh.sink  # noqa: F401
    import spiel_edge.outputs.udp  # noqa: F401
    import spiel_edge.outputs.zenoh  # noqa: F401
    import spiel_edge.outputs.zenoh_ros2  # noqa: F401
    import spiel_edge.recordings.ros2_mcap  # noqa: F401

    classes = (*_classes(Sink), McapSink, *_classes(McapSink))
    found = {c.__name__ for c in classes if c.__module__.startswith("spiel_edge.")}
    assert found <= {name.split("-")[0] for name in SINKS}, found


def test_the_table_opens_every_option():
    assert [option for option, _ in fanout.SINKS] == [
        "output",
        "record",
        "udp",
        "foxglove",
        "zenoh",
    ]


@pytest.mark.parametrize("name", sorted(SINKS))
def test_a_sink_keeps_the_contract(name, tmp_path, capsys):
    sink, path = SINKS[name](tmp_path)
    try:
        assert set(sink.capabilities) <= CAPABILITIES, sink.capabilities
        assert sink.owns_file == (FILE in sink.capabilities)
        assert sink.wants_acquisitions == (ACQUISITIONS in sink.capabilities)
        assert sink.alive
        sink.set_status_provider(lambda: {"state": "streaming"})
        sink.batch()
        assert sink.hold == (HOLD in sink.capabilities) or isinstance(sink, MultiSink)
        if sink.wants_acquisitions:
            sink.write_acquisition(dict(ACQUISITION), FRAMES)
        sink.write(dict(RECORD))
        if path is not None and HOLD in sink.capabilities:
            assert path.read_text() == ""  # held: nothing before flush
        sink.flush()
        if path is not None and HOLD in sink.capabilities:
            assert '"seq":0' in path.read_text()
        assert all(out.view_line for out in sink.parts() if "view" in out.capabilities)
    finally:
        sink.close()
    sink.close()  # again: no harm
    if FILE in sink.capabilities:
        assert path is not None and path.stat().st_size > 0, "FILE: a finalized file"
    elif path is None:
        assert not list(tmp_path.iterdir()), "not FILE: no file written"


class Failing(Sink):
    capabilities = frozenset({ACQUISITIONS})

    def write(self, record):
        raise OSError(28, "No space left on device")

    def write_acquisition(self, acquisition, frames):
        raise OSError(28, "No space left on device")


def test_a_fanout_counts_a_failing_output_and_keeps_the_others(tmp_path):
    good, path = _ndjson(tmp_path)
    sink = MultiSink([Failing(), good])
    sink.write_acquisition(dict(ACQUISITION), FRAMES)  # dropped here, not raised
    sink.write(dict(RECORD))
    sink.close()
    sink.close()
    assert sink.failed == ["Failing: No space left on device"] and sink.parts() == [good]
    assert '"seq":0' in path.read_text()
