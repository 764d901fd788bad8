"""A firmware that lies (issue 28, part 3): the virtual board's hostile modes
(``sim://?lie=MODE``, spiel_edge/sim/lies.py) contradict HELLO, STREAM_START or the stream's
own history. The host reports each at once, in one line naming the board, within the
documented bound, never waiting without end; the commands exit 2 with that line."""

from __future__ import annotations

import time
import uuid

import pytest

from spiel_edge.device import DeviceSession
from spiel_edge.device.sanity import MAX_BOARD_CONFIG_BYTES, FirmwareError
from spiel_edge.errors import DeviceError
from spiel_edge.sim import protocol_sim
from spiel_edge.sim.lies import HOSTILE_SERIAL, LIES

STREAM_LIES = {  # mode -> words of the message
    "channels": "5 channels (promised 4)",
    "fewer-channels": "3 channels (promised 4)",
    "samples": "samples (promised",
    "format": "sample format 1 (promised 0)",
    "channel-index": "channel 4 of 4",
    "counter-restart": "frame counter goes back",
    "index-repeat": "acquisition index repeats",
    "start-channels": "STREAM_START answered 5 channels, its HELLO 4",
}
SLOW_LIES = {  # found by the progress watch: within no_progress_limit_s()
    "incomplete": "no whole acquisition",
    "mute-stream": "sent no stream data",
}
CONFIG_LIES = {
    "endless-config": f"beyond {MAX_BOARD_CONFIG_BYTES} bytes",
    "oversized-config": "2036 bytes, 1018 were asked",
    "mute-config": "no answer to ConfigRead",
}
STALL_S = 0.1  # the session's stall period in these tests: the progress watch is 5 of them


def _url(lie: str, extra: str = "") -> str:
    """A fresh board per test (the name keeps the process's registry apart)."""
    return f"sim://lie-{uuid.uuid4().hex[:8]}?scene=model&lie={lie}{extra}"


@pytest.fixture(autouse=True)
def _forget_boards():
    yield
    protocol_sim.forget()


def _stream(url: str, count: int = 20, stall_s: float = STALL_S):
    with DeviceSession(url, reconnect=False, stall_s=stall_s) as session:
        session.start_stream(rate_hz=100)
        got = 0
        for _ in session.acquisitions():
            got += 1
            if got >= count:
                break
        return got


def _one_line_naming_the_board(message: str) -> None:
    assert "\n" not in message and "\x1b" not in message
    assert "board SIM0001" in message and "firmware sim-0.1.0" in message, message
    assert "a firmware bug" in message or "no answer" in message, message


@pytest.mark.parametrize("lie", sorted(STREAM_LIES))
def test_a_lying_stream_is_reported_at_once(lie):
    t0 = time.monotonic()
    with pytest.raises(FirmwareError) as info:
        _stream(_url(lie))
    assert time.monotonic() - t0 < 15  # at once: a few frames (seconds only on a loaded host)
    message = str(info.value)
    assert STREAM_LIES[lie] in message, message
    _one_line_naming_the_board(message)


@pytest.mark.parametrize("lie", sorted(SLOW_LIES))
def test_a_stream_without_progress_ends_within_its_bound(lie):
    with DeviceSession(_url(lie), reconnect=False, stall_s=STALL_S) as session:
        session.start_stream(rate_hz=100)
        limit = session.no_progress_limit_s()
        assert limit == pytest.approx(5 * STALL_S)
        t0 = time.monotonic()
        with pytest.raises(FirmwareError) as info:
            for _ in session.acquisitions():
                pass
        waited = time.monotonic() - t0
    assert waited < limit + 2 * STALL_S + 1.0, waited
    assert SLOW_LIES[lie] in str(info.value)
    _one_line_naming_the_board(str(info.value))


def test_the_progress_bound_follows_a_slow_rate():
    with DeviceSession(_url("mute-stream"), reconnect=False, stall_s=0.1) as session:
        session.start_stream(rate_hz=0.5)
        assert session.no_progress_limit_s() == pytest.approx(6.0)  # 3 periods of 2 s


@pytest.mark.parametrize("lie", sorted(CONFIG_LIES))
def test_a_lying_config_read_ends_with_one_line(lie):
    t0 = time.monotonic()
    with DeviceSession(_url(lie), reconnect=False) as session, pytest.raises(DeviceError) as info:
        session.read_config()
    assert time.monotonic() - t0 < 10
    message = str(info.value)
    assert CONFIG_LIES[lie] in message and "\n" not in message, message


def test_hello_strings_are_escaped():
    with DeviceSession(_url("hello-control"), reconnect=False) as session:
        assert session.hello.serial == HOSTILE_SERIAL.encode("unicode_escape").decode()
        assert not any(ord(c) < 32 for c in session.hello.serial + session.hello.firmware_version)


def test_an_honest_board_streams_on():
    """The checks cost an honest board nothing: 30 acquisitions, no error."""
    assert _stream(f"sim://honest-{uuid.uuid4().hex[:8]}?scene=model", count=30) == 30


def test_honest_line_faults_are_not_lies():
    """Lost, repeated and damaged frames (a bad cable) are counted, not refused."""
    url = f"sim://faults-{uuid.uuid4().hex[:8]}?scene=model&dup=0.2&drop=0.05&ber=0.0005"
    assert _stream(url, count=40) == 40


def test_every_lie_is_covered_here():
    elsewhere = {"hello-control", "start-at-ignored"}  # the latter: tests/robot/test_serve.py
    assert set(STREAM_LIES) | set(SLOW_LIES) | set(CONFIG_LIES) | elsewhere == set(LIES)


def test_an_unknown_lie_is_a_usage_error():
    from spiel_edge.errors import ConfigError
    from spiel_edge.link.sim_options import SimOptions

    with pytest.raises(ConfigError, match="lie must be one of"):
        SimOptions.from_url("sim://?lie=everything")


# --- through the commands -------------------------------------------------------------------


@pytest.mark.parametrize("lie", ["channels", "samples", "counter-restart", "start-channels"])
def test_run_ends_at_once_with_the_board_named(cli, tmp_path, lie):
    out = tmp_path / "o.ndjson"
    t0 = time.monotonic()
    ran = cli("run", "--port", _url(lie), "--frames", "50", "-o", out)
    assert ran.status == 2 and STREAM_LIES[lie] in ran.err, ran
    assert time.monotonic() - t0 < 30
    assert "board SIM0001" in ran.err


@pytest.mark.parametrize("lie", ["fewer-channels", "index-repeat"])
def test_background_ends_at_once_with_the_board_named(cli, tmp_path, lie):
    ran = cli("background", "--port", _url(lie), "-o", tmp_path / "bg.npy")
    assert ran.status == 2 and STREAM_LIES[lie] in ran.err, ran
    assert not (tmp_path / "bg.npy").exists()


@pytest.mark.parametrize("command", [["config", "pull"], ["config", "show"]])
@pytest.mark.parametrize("lie", ["endless-config", "oversized-config"])
def test_config_commands_end_on_an_endless_config(cli, tmp_path, command, lie):
    args = [*command, "--port", _url(lie)]
    if command[1] == "pull":
        args.append(tmp_path / "board.toml")
    ran = cli(*args)
    assert ran.status == 2 and CONFIG_LIES[lie] in ran.err, ran
    assert not (tmp_path / "board.toml").exists()


def test_run_shows_a_hostile_hello_escaped(cli, tmp_path):
    ran = cli("-v", "run", "--port", _url("hello-control"), "--frames", "3", "-o", tmp_path / "o")
    assert ran.status == 0, ran
    assert "\x1b" not in ran.err and "\x07" not in ran.err and "\\x1b" in ran.err
