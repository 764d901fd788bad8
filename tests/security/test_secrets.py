"""No secret in any output (issue 38, item 5): a Zenoh configuration that Zenoh refuses is
one line naming the file and where, never its values; client-driven log lines (a Foxglove
client connecting and disconnecting 300 times) are rate-limited."""

from __future__ import annotations

import logging
import socket
import time

import pytest

from spiel_edge.cli import main

zenoh = pytest.importorskip("zenoh", reason="the 'zenoh' extra is not installed")

PASSWORD = "hunter2-Secret-9f8e"
BAD_CONFIGS = {
    "wrong type": f'{{ transport: {{ auth: {{ usrpwd: {{ user: "robot", password: "{PASSWORD}", '
    "dictionary_file: 5 } } } }",
    "unquoted": f'{{ transport: {{ auth: {{ usrpwd: {{ user: "robot", password: {PASSWORD} }} }} }} }}',
    "bad mode": f'{{ transport: {{ auth: {{ usrpwd: {{ password: "{PASSWORD}" }} }} }}, mode: "x" }}',
    "password as a number": "{ transport: { auth: { usrpwd: { user: 'r', password: 918273645 } } } }",
    "unknown key": f'{{ transport: {{ auth: {{ usrpwd: {{ password: "{PASSWORD}", pw2: 1 }} }} }} }}',
    "not JSON5": f"password = {PASSWORD}\n",
}


@pytest.mark.parametrize("case", sorted(BAD_CONFIGS))
@pytest.mark.parametrize("command", ["run", "fuse"])
def test_a_refused_zenoh_config_never_shows_its_values(tmp_path, capsys, case, command):
    path = tmp_path / "zenoh.json5"
    path.write_text(BAD_CONFIGS[case])
    args = (
        ["run", "--port", "sim://", "--frames", "1", "--zenoh", "sec/k", "-o", str(tmp_path / "o")]
        if command == "run"
        else ["fuse", "--robot", "virtual-4", "--zenoh-config", str(path)]
    )
    if command == "run":
        import os

        os.environ["ZENOH_CONFIG"] = str(path)
    try:
        assert main(args) == 2
    finally:
        import os

        os.environ.pop("ZENOH_CONFIG", None)
    captured = capsys.readouterr()
    out = captured.out + captured.err
    assert PASSWORD not in out and "918273645" not in out
    assert "Traceback" not in out
    (line,) = [x for x in captured.err.splitlines() if x.strip()]
    assert str(path) in line


def test_client_log_lines_are_rate_limited(capsys):
    pytest.importorskip("foxglove", reason="extra 'foxglove' not installed")
    from spiel_edge.cli import setup_logging
    from spiel_edge.outputs.foxglove import FoxgloveSink
    from spiel_edge.runtime.log_limit import BURST

    setup_logging(1)  # -v: the SDK's per-client INFO lines too
    try:
        sink = FoxgloveSink("127.0.0.1:0")
        try:
            for i in range(300):  # connect and go away: half mid-handshake, half at once
                with socket.create_connection(("127.0.0.1", sink.port)) as c:
                    if i % 2:
                        c.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
            time.sleep(1.0)
        finally:
            sink.close()
    finally:
        logging.getLogger().handlers[0].filters.clear()
    lines = [x for x in capsys.readouterr().err.splitlines() if "foxglove." in x]
    kinds = {(x.split()[2], x.split()[3]) for x in lines if len(x.split()) > 3}
    assert lines, "the SDK logged nothing: the test proves nothing"
    assert len(lines) <= BURST * max(1, len(kinds)) + 4, len(lines)
    assert len(lines) < 40


def test_the_limiter_lets_a_burst_through_then_counts_what_it_held():
    from spiel_edge.runtime.log_limit import BURST, WINDOW_S, ClientLogLimiter

    now = [0.0]
    limiter = ClientLogLimiter(clock=lambda: now[0])

    def line(name="foxglove.websocket.server", msg="Dropping client"):
        rec = logging.LogRecord(name, logging.ERROR, __file__, 1, msg, None, None)
        return limiter.filter(rec), rec.getMessage()

    passed = [line() for _ in range(300)]
    assert sum(ok for ok, _ in passed) == BURST and "held back" in passed[BURST - 1][1]
    assert all(line("spiel_edge.outputs.foxglove")[0] for _ in range(50))  # ours: not limited
    now[0] += WINDOW_S
    ok, text = line()
    assert ok and f"{300 - BURST} more such lines held back" in text


def test_zenoh_errors_never_carry_a_loaded_user_or_password(tmp_path):
    from spiel_edge.outputs.zenoh import load_config, zenoh_reason

    path = tmp_path / "z.json5"
    path.write_text(
        f'{{ transport: {{ auth: {{ usrpwd: {{ user: "rover-7", password: "{PASSWORD}" }} }} }} }}'
    )
    load_config(str(path))
    text = zenoh_reason(RuntimeError(f"auth of rover-7 with {PASSWORD} refused\nat x.rs:3"))
    assert PASSWORD not in text and "rover-7" not in text and "\n" not in text
