"""MCAP recordings: round trip, replay through the CLI, damaged files, SIGTERM."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from mcap.reader import make_reader

from spiel_edge.cli import main
from spiel_edge.data import load_subset
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile
from spiel_edge.recordings.mcap_reader import (
    ACQUISITION_TOPIC,
    BACKGROUND_TOPIC,
    POSITION_TOPIC,
    iter_mcap_recordings,
    recording_metadata,
)
from spiel_edge.recordings.mcap_writer import McapSink

N = 12


@pytest.fixture(scope="module")
def subset():
    return load_subset()


def _record(path, subset, n=N, metadata=None):
    """The vendored acquisitions as a live run writes them: acquisition, then its record."""
    with McapSink(path, metadata=metadata or {"profile": "spiel-icra23"}) as sink:
        for i in range(n):
            acq = {
                "seq": 100 + i,
                "timestamp_ns": 1_000_000 + i,
                "background": subset.backgrounds[i],
            }
            sink.write_acquisition(acq, subset.frames[i])
            sink.write({"seq": 100 + i, "position_mm": [float(i), 0.0, 100.0], "reason": None})
    return path


def test_round_trip_frames_backgrounds_sources(tmp_path, subset):
    path = _record(tmp_path / "r.mcap", subset)
    recs = list(iter_mcap_recordings(path))
    assert [r.source for r in recs] == [f"r.mcap#{100 + i}" for i in range(N)]
    assert all(r.error is None for r in recs)
    for i, r in enumerate(recs):
        np.testing.assert_array_equal(r.frames, subset.frames[i])
        np.testing.assert_array_equal(r.background, subset.backgrounds[i])


def test_channels_schemas_and_summary_for_other_tools(tmp_path, subset):
    path = _record(tmp_path / "r.mcap", subset)
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {ACQUISITION_TOPIC, BACKGROUND_TOPIC, POSITION_TOPIC}
        for channel in topics.values():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            assert json.loads(schema.data)["type"] == "object"
        counts = {
            topics_id: n for topics_id, n in summary.statistics.channel_message_counts.items()
        }
        by_topic = {summary.channels[cid].topic: n for cid, n in counts.items()}
        distinct_backgrounds = len({b.tobytes() for b in subset.backgrounds[:N]})
        assert by_topic == {
            ACQUISITION_TOPIC: N,
            POSITION_TOPIC: N,
            BACKGROUND_TOPIC: distinct_backgrounds,
        }
        positions = [
            json.loads(m.data) for _, _, m in reader.iter_messages(topics=[POSITION_TOPIC])
        ]
        assert [p["position_mm"][0] for p in positions] == [float(i) for i in range(N)]
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        assert metadata["spiel-edge"]["profile"] == "spiel-icra23"


def test_background_written_once_while_unchanged(tmp_path, subset):
    path = tmp_path / "r.mcap"
    with McapSink(path) as sink:
        for i in range(5):
            sink.write_acquisition(
                {"seq": i, "background": subset.backgrounds[0]}, subset.frames[i]
            )
    recs = list(iter_mcap_recordings(path))
    with open(path, "rb") as fh:
        counts = make_reader(fh).get_summary().statistics.channel_message_counts
    assert sorted(counts.values()) == [1, 5]
    assert all(np.array_equal(r.background, subset.backgrounds[0]) for r in recs)


def test_replay_command_matches_the_pipeline(tmp_path, subset):
    path = _record(tmp_path / "r.mcap", subset)
    out = tmp_path / "out.ndjson"
    assert main(["replay", str(path), "--association", "geometric", "-o", str(out)]) == 0
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    pipeline = build_pipeline(load_profile("spiel-icra23"), "geometric")
    assert len(lines) == N
    for i, line in enumerate(lines):
        expected = pipeline.process(subset.frames[i], subset.backgrounds[i]).record()
        assert line["source"] == f"r.mcap#{100 + i}"
        assert (
            line["position_mm"] == expected["position_mm"] and line["reason"] == expected["reason"]
        )
    assert sum(line["position_mm"] is not None for line in lines) >= N // 2  # real data locates


def test_metadata_is_read_back_and_a_bad_head_reads_as_none(tmp_path, subset):
    path = _record(tmp_path / "m.mcap", subset, 2, {"port": "sim://?scene=model", "x": "y"})
    meta = recording_metadata(path)
    assert meta["port"] == "sim://?scene=model" and meta["x"] == "y" and "version" in meta
    raw = bytearray(path.read_bytes())
    at = raw.index(b"port") - 4
    raw[at : at + 4] = (1 << 30).to_bytes(4, "little")  # a key longer than its record
    (tmp_path / "bad.mcap").write_bytes(raw)
    (tmp_path / "text.mcap").write_text("not mcap")
    for name in ("bad.mcap", "text.mcap", "missing.mcap"):
        assert recording_metadata(tmp_path / name) == {}


def test_replay_uses_the_toa_correction_the_recording_was_made_with(tmp_path, subset):
    path = _record(tmp_path / "r.mcap", subset, metadata={"toa_correction": "none"})
    profile, geometric = load_profile("spiel-icra23"), ["--association", "geometric"]
    runs = {}
    for flag in ([], ["--toa-correction", "auto"]):
        out = tmp_path / f"out{len(flag)}.ndjson"
        assert main(["replay", str(path), *geometric, *flag, "-o", str(out)]) == 0
        runs[tuple(flag)] = [
            json.loads(line)["position_mm"] for line in out.read_text().splitlines()
        ]
    for flag, correction in (((), "none"), (("--toa-correction", "auto"), "auto")):
        pipeline = build_pipeline(profile, "geometric", correction)
        expected = [
            pipeline.process(subset.frames[i], subset.backgrounds[i]).record()["position_mm"]
            for i in range(N)
        ]
        assert runs[flag] == expected
    assert runs[()] != runs[("--toa-correction", "auto")]  # the choice changes positions


def test_unfinalized_file_replays_up_to_its_end(tmp_path, subset):
    path = _record(tmp_path / "r.mcap", subset)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) - 40])  # footer and part of the summary gone
    recs = list(iter_mcap_recordings(cut))
    assert [r.error is None for r in recs] == [True] * N + [False]
    assert "ends early after 12 acquisitions" in recs[-1].error
    out = tmp_path / "out.ndjson"
    assert main(["replay", str(cut), "--association", "geometric", "-o", str(out)]) == 1  # partial


def test_not_an_mcap_file(tmp_path, capsys):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"PK\x03\x04 not a recording")
    assert main(["replay", str(bad)]) == 2
    assert "not an MCAP file" in capsys.readouterr().err


def test_bad_messages_become_error_entries(tmp_path, subset):
    path = tmp_path / "r.mcap"
    with McapSink(path) as sink:
        sink.write_acquisition({"seq": 0}, subset.frames[0])
        sink.write_acquisition({"seq": 1}, np.full((4, 64), np.nan))
        sink._add(ACQUISITION_TOPIC, {"seq": 2, "frames": [[1, 2], [3]]}, 0)  # ragged
        sink._add(ACQUISITION_TOPIC, {"seq": 3}, 0)  # no frames
        sink.write_acquisition({"seq": 4}, subset.frames[4])
    recs = list(iter_mcap_recordings(path))
    assert [r.error is None for r in recs] == [True, False, False, False, True]
    assert "non-finite" in recs[1].error and recs[2].source == "r.mcap#2"


def test_finalized_when_an_exception_escapes(tmp_path, subset):
    path = tmp_path / "r.mcap"
    with pytest.raises(RuntimeError), McapSink(path) as sink:
        sink.write_acquisition({"seq": 0}, subset.frames[0])
        raise RuntimeError("pipeline blew up")
    with open(path, "rb") as fh:
        assert make_reader(fh).get_summary().statistics.message_count == 1
    with pytest.raises(ValueError, match="closed"):
        sink.write({"seq": 1})


def test_the_sink_installs_no_signal_handler(tmp_path):
    """Sinks own only their files: the command line owns signals."""
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    with McapSink(tmp_path / "a.mcap"):
        assert {sig: signal.getsignal(sig) for sig in before} == before


_WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from spiel_edge.cli._signals import terminate_raises
    from spiel_edge.recordings.mcap_writer import McapSink
    sink = McapSink(sys.argv[1])
    frames = np.arange(256, dtype=np.float64).reshape(4, 64)
    n = 0
    try:
        with terminate_raises():
            while True:
                sink.write_acquisition({"seq": n}, frames)
                sink.write({"seq": n, "position_mm": None})
                n += 1
                if n == 50:
                    print("ready", flush=True)
                time.sleep(0.002)
    finally:
        sink.close()
        print(n, flush=True)
""")


def test_sigterm_finalizes_a_recording(tmp_path):
    """A writer that turns SIGTERM into an exception (the CLI's helper) gets a finalized file."""
    path = tmp_path / "r.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout.readline().strip() == "ready"
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=10)
    finally:
        proc.kill()
    written = int(out.split()[-1])
    assert proc.returncode != 0  # stopped by the signal, not a normal end
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()  # None or an error if not finalized
    assert summary is not None and summary.statistics.message_count == 2 * written
    recs = list(iter_mcap_recordings(path))
    assert len(recs) == written and all(r.error is None for r in recs)
