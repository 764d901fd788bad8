"""No raw control character reaches a terminal or a log (issue 43): strings from a board (HELLO,
firmware slots), an image (version, target), a file name or the network (Zenoh keys) pass
through the one escaping function, spiel_edge.safety.shown.escape."""

from __future__ import annotations

import logging
import re

import pytest

from spiel_edge.cli import main, shorten_record
from spiel_edge.safety.shown import escape
from tests.fwsign import DEV_KEY, signed_image
from tests.protocol_v2.conftest import sim_url  # noqa: F401  # a fixture: fresh boards

# ESC + CSI (clear screen), BEL, OSC (window title), a newline, C1 CSI, a byte that was not UTF-8
HOSTILE = ["\x1b[2J", "\x07", "\x1b]0;pwned\x07", "a\nb", "\x9b31m", "\udcff"]
RAW = re.compile(r"[\x00-\x08\x0b-\x1f\x7f-\x9f\ud800-\udfff]")  # what must never get out


def _raw_in(text: str) -> list[str]:
    """Raw control characters of ``text`` (line ends between lines of ours are fine, and so
    is the carriage return of update's own progress line)."""
    return RAW.findall(text.replace("\r  ", "  "))


@pytest.mark.parametrize("text", HOSTILE)
def test_escape_shows_every_control_character(text) -> None:
    shown = escape(text)
    assert not _raw_in(shown) and "\n" not in shown, repr(shown)
    assert escape(text.encode("utf-8", "surrogateescape")) == shown  # bytes alike


def test_firmware_pack_update_and_info_escape_the_image_strings(sim_url, tmp_path, capsys):  # noqa: F811 (the fixture)
    body = tmp_path / "body.bin"
    body.write_bytes(b"SIM:OK " + bytes(range(256)) * 4)
    hostile_version = "1\x1b[2J\x07"  # 6 bytes: fits the 16 of the header
    image = tmp_path / "fw.img"
    status = main(
        [
            "firmware",
            "pack",
            str(body),
            "--version",
            hostile_version,
            "--target",
            "sim",
            "--key",
            str(DEV_KEY),
            "-o",
            str(image),
        ]
    )
    out, err = capsys.readouterr()
    assert status == 0 and not _raw_in(out + err) and "\\x1b[2J\\x07" in err, err
    url = sim_url("max_payload=512")
    status = main(["firmware", "update", "--port", url, "--wait", "10", str(image)])
    out, err = capsys.readouterr()
    assert not _raw_in(out + err), (out, err)
    assert "\\x1b[2J" in err, err  # shown, not obeyed
    main(["firmware", "info", "--port", url])
    out, err = capsys.readouterr()
    assert not _raw_in(out + err) and "\\x1b[2J\\x07" in out, (out, err)


def test_a_hostile_target_and_a_non_utf8_file_name_in_errors(sim_url, tmp_path, capsys):  # noqa: F811 (the fixture)
    image = tmp_path / "fw.img"
    image.write_bytes(signed_image(b"SIM:OK " + bytes(256), version="2.0", target="e\x1b[31mvil"))
    assert main(["firmware", "update", "--port", sim_url(), str(image)]) == 2
    out, err = capsys.readouterr()
    assert not _raw_in(out + err) and "\\x1b[31m" in err, err
    missing = str(tmp_path) + "/no\udcff\x1b[2Jsuch\n.img"
    assert main(["firmware", "update", "--port", sim_url(), missing]) == 2
    out, err = capsys.readouterr()
    assert not _raw_in(out + err) and err.count("\n") == 1 and "\\xff" in err, err


def test_every_log_record_is_one_escaped_line() -> None:
    """The CLI's log filter: a board's log line, a Zenoh key, a robot's board name."""
    record = logging.LogRecord(
        "spiel_edge.outputs.zenoh", logging.WARNING, __file__, 1, "key %s: %s", None, None
    )
    record.args = ("robot/\x1b[2J/targets", "board\nFAKE LINE \x07")
    assert shorten_record(record)
    message = record.getMessage()
    assert not _raw_in(message) and "\n" not in message, repr(message)
    assert "robot/\\x1b[2J/targets" in message and "board\\nFAKE LINE \\x07" in message


def test_last_rounds_unclear_messages_are_one_clear_line(sim_url, tmp_path, capsys):  # noqa: F811 (the fixture)
    """A newline in a missing input's name, a non-UTF-8 folder for an MCAP output, an endless
    board config read: each one line naming what and where, status 2, quickly."""
    assert main(["replay", str(tmp_path / "no\nsuch.csv")]) == 2
    err = capsys.readouterr().err
    assert "no\\nsuch.csv" in err and "does not exist" in err and not _raw_in(err), err
    folder = str(tmp_path / "nod\udcff") + "/out.mcap"
    port = "sim://?scene=model"
    assert (
        main(["run", "--port", port, "--frames", "3", "--record", folder, "-o", "/dev/null"]) == 2
    )
    err = capsys.readouterr().err
    assert "--record" in err and "nod\\xff does not exist" in err and err.count("\n") == 1, err
    good = tmp_path / "d\udcff"
    good.mkdir()  # an existing non-UTF-8 folder is just a folder
    out = str(good) + "/out.mcap"
    assert main(["run", "--port", port, "--frames", "3", "--record", out, "-o", "/dev/null"]) == 0
    capsys.readouterr()
    assert main(["config", "pull", "--port", sim_url("lie=endless-config")]) == 2
    err = capsys.readouterr().err
    assert "config goes on beyond" in err and err.count("\n") == 1, err


def test_doctor_shows_what_its_checks_found_escaped(monkeypatch, capsys) -> None:
    """A check's detail and fix carry paths, environment values and exception texts: a path
    holding an escape sequence is shown, never sent to the terminal."""
    from spiel_edge.cli import doctor
    from spiel_edge.service.host_checks import Check

    hostile = "/srv/\x1b]0;owned\x07cache\x1b[2J"
    found = [Check("numba cache", False, f"{hostile}: not writable", f"chmod u+w {hostile}")]
    monkeypatch.setattr(doctor, "run_checks", lambda *a, **k: found)
    assert main(["doctor", "--skip-numba"]) == 1
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\x07" not in out
    assert "\\x1b]0;owned\\x07cache\\x1b[2J: not writable" in out and "fix: chmod u+w /srv/" in out
