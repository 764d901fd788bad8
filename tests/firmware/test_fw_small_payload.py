"""A board whose HELLO says max_payload 256 (the spec allows it; one 4 x 64 stream frame is 152
bytes) works with every host command, on both virtual boards: the Python one
(`sim://...?max_payload=256`) and the C firmware built with -DSPIEL_MAX_PAYLOAD=256. Config
chunks are sized from the link's max_payload (250 bytes), never the old fixed 1024. The same
commands work with version-1 boards (`?protocol=1`, -DSPIEL_PROTOCOL_MAX=1)."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from spiel_edge.calibrate.capture import capture_positions
from spiel_edge.cli import main
from spiel_edge.device import DeviceSession
from spiel_edge.errors import DeviceRequestError
from spiel_edge.profile.schema import load_profile
from spiel_edge.protocol import ConfigRead, ConfigSource
from tests.firmware.firmware import build_posix

_names = itertools.count()


BOARDS = {  # name: (sim query, C build defines, HELLO max_payload, protocol version)
    "python-256": ("max_payload=256", None, 256, 2),
    "c-256": (None, {"SPIEL_MAX_PAYLOAD": 256}, 256, 2),
    "python-v1": ("protocol=1", None, 8256, 1),
    "c-v1": (None, {"SPIEL_PROTOCOL_MAX": 1}, 1024, 1),
}


@pytest.fixture(params=sorted(BOARDS))
def small_board(request, posix_board, fw_build):
    query, defines, payload, version = BOARDS[request.param]
    if query is not None:
        from spiel_edge.sim import protocol_sim

        url = f"sim://small-{next(_names)}?{query}"
        yield url, payload, version
        protocol_sim.forget(url)
    else:
        yield posix_board(exe=build_posix(fw_build, **defines)).port, payload, version


def test_every_host_command_works(small_board, tmp_path, capsys):
    port, payload, version = small_board
    with DeviceSession(port, reconnect=False) as session:
        assert session.hello.max_payload == session.max_payload == payload
        assert session.protocol_version == version and session.config_chunk == payload - 6
        with pytest.raises(DeviceRequestError, match="TOO_LARGE"):
            session.request(ConfigRead(0, payload - 5, ConfigSource.STAGING))  # board's check
    partial = tmp_path / "name.toml"
    partial.write_text('[board]\nname = "small-payload"\n')
    assert main(["config", "push", "--port", port, str(partial)]) == 0
    assert main(["config", "commit", "--port", port]) == 0
    pulled = tmp_path / "pulled.toml"
    assert main(["config", "pull", "--port", port, str(pulled)]) == 0
    assert 'name = "small-payload"' in pulled.read_text()
    if payload == 256:
        assert len(pulled.read_text()) > 250  # the blob took more than one chunk each way
    assert main(["config", "show", "--port", port]) == 0
    assert main(["config", "diff", "--port", port, str(pulled)]) == 0
    capsys.readouterr()
    out = tmp_path / "run.ndjson"
    assert main(["run", "--port", port, "--frames", "20", "--rate", "200", "-o", str(out)]) == 0
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(recs) == 20 and sum(r["position_mm"] is not None for r in recs) >= 10
    npy = tmp_path / "bg.npy"
    assert main(["background", "--port", port, "--frames", "3", "-o", str(npy)]) == 0
    assert np.load(npy).shape == (4, 64)
    profile = load_profile("spiel-icra23")
    with DeviceSession(port, reconnect=False) as session:  # calibrate's capture
        frames, backgrounds, truth = capture_positions(
            session,
            profile,
            np.array([[0.0, 0.0, 150.0], [20.0, 0.0, 150.0]]),
            captures=3,
            before_position=lambda i, p: None,
        )
    assert frames.shape == backgrounds.shape == (6, 4, 64) and truth.shape == (6, 3)
    capsys.readouterr()
    main(["doctor", "--port", port, "--skip-numba", "--json"])  # other checks may fail here
    [link] = [c for c in json.loads(capsys.readouterr().out)["checks"] if c["name"] == "board link"]
    assert link["ok"] and f"max_payload {payload}," in link["detail"]
    assert f"protocol {version} " in link["detail"]
