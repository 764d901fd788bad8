"""The live echogram: a waterfall of A-scans with the echoes marked, on Foxglove's
/spiel/echogram as foxglove.RawImage, and the layout file that shows it."""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path

import numpy as np
import pytest

from spiel_edge.outputs.echogram import ECHO_RGB, MATCH_RGB, SEPARATOR_RGB, Echogram

ROOT = Path(__file__).resolve().parents[2]


def test_rows_scroll_and_echo_marks_sit_at_the_records_times():
    gram = Echogram(rows=8)
    frames = np.zeros((4, 64))
    frames[1, 30] = 100.0
    echoes = [[10.2], [29.6, 50.0], [], [63.0]]
    image = gram.add(frames, None, echoes, matched=[None, 0, None, None])
    assert image.shape == (8, 4 * 64 + 3, 3) and image.dtype == np.uint8
    assert tuple(image[0, Echogram.column(0, 10.2, 64)]) == ECHO_RGB
    assert tuple(image[0, Echogram.column(1, 29.6, 64)]) == MATCH_RGB  # the matched one
    assert tuple(image[0, Echogram.column(1, 50.0, 64)]) == ECHO_RGB
    assert tuple(image[0, Echogram.column(3, 63.0, 64)]) == ECHO_RGB
    red = np.all(image[0] == ECHO_RGB, axis=1).sum() + np.all(image[0] == MATCH_RGB, axis=1).sum()
    assert red == 4  # every echo once, nothing else
    assert not image[1:].any()  # one acquisition: one row
    second = gram.add(frames * 0.5, None, [[], [], [], []])
    assert np.array_equal(second[1], image[0])  # the older row moved down
    assert second[0, Echogram.column(1, 30, 64)].tolist() == [127, 127, 127]  # half the peak


def test_the_background_is_subtracted_and_bad_times_ignored():
    gram = Echogram(rows=2)
    frames = np.full((2, 16), 50.0)
    image = gram.add(frames, np.full((2, 16), 50.0), [[float("nan"), 99.0], [-1.0]])
    separator = np.all(image == SEPARATOR_RGB, axis=2)
    assert separator.sum() == 1 and not image[~separator].any()  # only the divider, one row


def test_foxglove_serves_the_echogram_and_the_layout_names_its_topics():
    pytest.importorskip("foxglove", reason="extra 'foxglove' not installed")
    from spiel_edge.outputs.foxglove import ECHOGRAM_TOPIC, FoxgloveSink
    from tests.headless._ws import MiniWebSocket

    sink = FoxgloveSink("0")
    ws = MiniWebSocket("127.0.0.1", sink.port, "foxglove.sdk.v1")
    frames = np.zeros((4, 64))
    record = {"echoes": [[20.0], [21.0], [22.0], [23.0]], "matched": [0, 0, 0, 0], "targets": []}
    try:
        channels: dict[str, dict] = {}
        deadline = time.monotonic() + 5
        while ECHOGRAM_TOPIC not in channels and time.monotonic() < deadline:
            message = json.loads(ws.recv()[1])
            if message["op"] == "advertise":
                channels.update({c["topic"]: c for c in message["channels"]})
        assert channels[ECHOGRAM_TOPIC]["schemaName"] == "foxglove.RawImage"
        ws.send_json(
            {
                "op": "subscribe",
                "subscriptions": [{"id": 1, "channelId": channels[ECHOGRAM_TOPIC]["id"]}],
            }
        )
        payload = None
        while payload is None and time.monotonic() < deadline:
            sink.write_acquisition({"background": None}, frames)
            sink.write(record)
            frame = ws.recv(wait_s=0.1)
            if frame is not None and frame[0] == 2 and frame[1][0] == 1:
                assert struct.unpack_from("<I", frame[1], 1)[0] == 1
                payload = frame[1][13:]
        assert payload is not None
        row = sink._echogram.image[0].tobytes()  # the newest row travels inside the image
        assert row in payload and b"rgb8" in payload
    finally:
        ws.close()
        sink.close()
    layout = json.loads((ROOT / "packaging" / "foxglove" / "spiel-edge.json").read_text())
    text = json.dumps(layout["configById"])
    for topic in (ECHOGRAM_TOPIC, "/spiel/scene", "/spiel/position"):
        assert topic in text
    panels = set(layout["configById"])
    assert {layout["layout"]["first"], *layout["layout"]["second"].values()} & panels == panels


def test_run_says_where_the_live_view_is_without_v(tmp_path, capsys):
    pytest.importorskip("foxglove", reason="extra 'foxglove' not installed")
    from spiel_edge.cli import main

    out = tmp_path / "r.ndjson"
    assert (
        main(["run", "--port", "sim://", "--frames", "3", "--foxglove", "0", "-o", str(out)]) == 0
    )
    err = capsys.readouterr().err
    assert "Foxglove live view on ws://127.0.0.1:" in err and "spiel-edge.json" in err
