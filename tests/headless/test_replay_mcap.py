"""`replay -o FILE.mcap`: a recording laid out as `run --record` writes it (JSON, or ROS 2 CDR
read back by rosbags), with /tf_static from the profile's [frame] or the options, under the
file rules of safety/guard.py (no overwrite without --force, moved into place when finalized, a
signal finalizes it)."""

from __future__ import annotations

import json
import math
import os
import signal

import numpy as np
import pytest

from spiel_edge.cli import main
from spiel_edge.profile.schema import dump_toml, load_profile, profile_to_dict
from spiel_edge.recordings.mcap_reader import POSITION_TOPIC, iter_mcap_recordings
from spiel_edge.recordings.mcap_scan import MAGIC
from spiel_edge.recordings.mcap_writer import McapSink

rosbags = pytest.importorskip("rosbags", reason="rosbags is in the 'test' extra")
from rosbags.highlevel import AnyReader  # noqa: E402

N = 50
T0_NS = 1_796_000_000_000_000_000
GEOMETRIC = ["--association", "geometric"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, subset):
    """50 vendored acquisitions as `run --record` writes them, 20 ms apart."""
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    with McapSink(path) as sink:
        for i in range(N):
            acq = {"seq": i, "timestamp_ns": T0_NS + i * 20_000_000}
            sink.write_acquisition({**acq, "background": subset.backgrounds[i]}, subset.frames[i])
            sink.write({"seq": i, "position_mm": None})
    return path


@pytest.fixture(scope="module")
def replayed(recorded, tmp_path_factory):
    """The recording replayed to NDJSON: what every MCAP replay must reproduce."""
    out = tmp_path_factory.mktemp("nd") / "ref.ndjson"
    assert main(["replay", str(recorded), *GEOMETRIC, "-o", str(out)]) == 0
    return [json.loads(line) for line in out.read_text().splitlines()]


def _positions(records):
    return [r["position_mm"] for r in records]


def test_json_mcap_keeps_frames_times_and_replays_again(recorded, replayed, tmp_path):
    out = tmp_path / "re.mcap"
    assert main(["replay", str(recorded), *GEOMETRIC, "-o", str(out)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["re.mcap"]  # no temporary left
    again = list(iter_mcap_recordings(out))
    original = list(iter_mcap_recordings(recorded))
    assert len(again) == N and all(r.error is None for r in again)
    for a, b in zip(again, original, strict=True):
        np.testing.assert_array_equal(a.frames, b.frames)
        np.testing.assert_array_equal(a.background, b.background)
        assert a.time_s == pytest.approx(b.time_s, abs=1e-6)
    records = _mcap_records(out)
    assert [r["seq"] for r in records] == list(range(N))
    assert records[1]["host_time"] - records[0]["host_time"] == pytest.approx(0.02, abs=1e-5)
    assert _positions(records) == _positions(replayed)
    twice = tmp_path / "twice.ndjson"
    assert main(["replay", str(out), *GEOMETRIC, "-o", str(twice)]) == 0
    assert _positions(json.loads(x) for x in twice.read_text().splitlines()) == _positions(replayed)


def _mcap_records(path):
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        return [
            json.loads(m.data)
            for _s, c, m in make_reader(fh).iter_messages(topics=[POSITION_TOPIC])
            if c.topic == POSITION_TOPIC
        ]


def _frame_profile(tmp_path, **frame):
    data = profile_to_dict(load_profile())
    data["frame"] = {**data["frame"], **frame}
    path = tmp_path / "mounted.toml"
    path.write_text(dump_toml(data))
    return path


def test_ros2_mcap_with_profile_frame_read_by_rosbags_and_replayed(recorded, replayed, tmp_path):
    profile = _frame_profile(
        tmp_path,
        frame_id="sonar",
        parent="base_link",
        translation_m=[0.1, 0.0, 0.25],
        rotation_rpy_deg=[0.0, 0.0, 90.0],
    )
    out = tmp_path / "ros2.mcap"
    args = ["replay", str(recorded), *GEOMETRIC, "--profile", str(profile)]
    assert main([*args, "-o", str(out), "--record-profile", "ros2"]) == 0
    fixes = [p for p in _positions(replayed) if p is not None]
    with AnyReader([out]) as reader:
        by_topic = {c.topic: c for c in reader.connections}
        points = [
            reader.deserialize(raw, c.msgtype)
            for c, _t, raw in reader.messages(connections=[by_topic["/spiel/point"]])
        ]
        (tf_message,) = [
            reader.deserialize(raw, c.msgtype)
            for c, _t, raw in reader.messages(connections=[by_topic["/tf_static"]])
        ]
        first = next(reader.messages())
    assert len(points) == len(fixes) > 40
    assert all(p.header.frame_id == "sonar_optical" for p in points)  # REP 103: z forward
    np.testing.assert_allclose(
        [[p.point.x, p.point.y, p.point.z] for p in points], np.array(fixes) / 1e3, atol=1e-9
    )
    stamp = points[0].header.stamp
    assert stamp.sec == T0_NS // 10**9  # the recorded capture time, not the replay's
    assert first[0].topic == "/tf_static"  # first in the file, at the first acquisition's time
    tf, optical = tf_message.transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("base_link", "sonar")
    assert (optical.header.frame_id, optical.child_frame_id) == ("sonar", "sonar_optical")
    assert (tf.transform.translation.x, tf.transform.translation.z) == (0.1, 0.25)
    q = tf.transform.rotation
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], [0, 0, math.sqrt(0.5), math.sqrt(0.5)])
    back = tmp_path / "back.ndjson"
    assert main(["replay", str(out), *GEOMETRIC, "-o", str(back)]) == 0
    assert _positions(json.loads(x) for x in back.read_text().splitlines()) == _positions(replayed)


def test_options_override_the_profile_frame(recorded, tmp_path):
    out = tmp_path / "o.mcap"
    args = ["replay", str(recorded), *GEOMETRIC, "-o", str(out), "--record-profile", "ros2"]
    args += ["--parent-frame", "odom", "--rotation-xyzw", "0,0,0.7071068,0.7071068"]
    assert main(args) == 0
    with AnyReader([out]) as reader:
        statics = [c for c in reader.connections if c.topic == "/tf_static"]
        (message,) = [reader.deserialize(r, c.msgtype) for c, _t, r in reader.messages(statics)]
    tf, _optical = message.transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("odom", "spiel")
    assert tf.transform.rotation.z == pytest.approx(math.sqrt(0.5), abs=1e-7)


def test_no_overwrite_without_force(recorded, tmp_path, capsys):
    out = tmp_path / "keep.mcap"
    out.write_bytes(b"precious")
    assert main(["replay", str(recorded), *GEOMETRIC, "-o", str(out)]) == 2
    assert out.read_bytes() == b"precious"
    assert "exists; pass --force" in capsys.readouterr().err
    assert main(["replay", str(recorded), *GEOMETRIC, "-o", str(out), "--force"]) == 0
    assert len(list(iter_mcap_recordings(out))) == N
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.mcap"]


def test_bad_frame_options_fail_before_work_in_one_line(recorded, tmp_path, capsys):
    out = tmp_path / "x.mcap"
    for bad in (
        ["--parent-frame", "b", "--translation-m", "0,0,250"],
        ["--translation-m", "0,0,1"],  # no parent
        ["--parent-frame", "spiel"],
        ["--parent-frame", "b", "--rotation-xyzw", "0,0,0,3"],
        ["--frame-id", "/spiel"],
    ):
        capsys.readouterr()
        assert main(["replay", str(recorded), "-o", str(out), *bad]) == 2, bad
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and "\n" not in err and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []


def test_a_signal_finalizes_the_recording(recorded, tmp_path, monkeypatch, capsys):
    """SIGTERM in the middle: the MCAP holds what was replayed, finalized, in place; status 1."""
    import spiel_edge.cli.replay as command

    real = command.replay

    def interrupted(pipeline, sources):
        for n, item in enumerate(real(pipeline, sources)):
            if n == 10:
                os.kill(os.getpid(), signal.SIGTERM)
            yield item

    monkeypatch.setattr(command, "replay", interrupted)
    out = tmp_path / "cut.mcap"
    assert main(["replay", str(recorded), *GEOMETRIC, "-o", str(out)]) == 1
    assert out.read_bytes().endswith(MAGIC)  # finalized (summary and footer written)
    recs = list(iter_mcap_recordings(out))
    assert len(recs) == 11 and all(r.error is None for r in recs)
    assert "stopped by a signal" in capsys.readouterr().err


def test_a_file_that_appears_during_the_replay_is_not_replaced(tmp_path):
    from spiel_edge.errors import ConfigError
    from spiel_edge.runtime.recorded_output import ReplayMcap

    target = tmp_path / "late.mcap"
    out = ReplayMcap(target, force=False)
    target.write_bytes(b"someone else's")  # after the command's checks, before the move
    with pytest.raises(ConfigError, match="appeared during the replay"):
        out.close()
    assert target.read_bytes() == b"someone else's"
    assert [p.name for p in tmp_path.iterdir()] == ["late.mcap"]  # no temporary left
    forced = ReplayMcap(target, force=True)
    forced.discard()  # a failed replay: the target stays as it was
    assert target.read_bytes() == b"someone else's"
    assert [p.name for p in tmp_path.iterdir()] == ["late.mcap"]
