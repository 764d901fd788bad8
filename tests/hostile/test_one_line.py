"""One line, always (issue 28, part 5): odd file names are shown escaped (control characters,
newlines, bytes that are not UTF-8, bidirectional overrides), a closed stdout is a one-line
error, library warnings never reach the terminal raw, no input gives `internal error`."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from spiel_edge.safety.guard import escape, shorten

CLI = [sys.executable, "-m", "spiel_edge.cli"]
NO_BOARD = "serial:///nonexistent/tty-spiel"

NAMES = {
    "newline": ("bad\nname", "bad\\nname"),
    "carriage-return": ("over\rwrite", "over\\rwrite"),
    "escape-sequence": ("clear\x1b[2Jscreen", "clear\\x1b[2Jscreen"),
    "bell": ("ring\x07", "ring\\x07"),
    "not-utf8": (os.fsdecode(b"caf\xe9\xff"), "caf\\xe9\\xff"),
    "bidi-override": ("txt.\u202eexe", "txt.\\u202eexe"),
    "line-separator": ("a\u2028b", "a\\u2028b"),
    "tab": ("a\tb", "a\\tb"),
    "nul-like-c1": ("a\x85b", "a\\x85b"),
    "very-long": ("n" * 250, "characters)"),
}


def _clean_line(err: str) -> str:
    """The message line: the only line, or the `Error:` line of a usage message (click's
    usage errors say `Usage:` and `Try ... --help` above it)."""
    lines = [line for line in err.strip().splitlines() if line]
    if lines[0].startswith("Usage:"):
        assert len(lines) == 3 and lines[1].startswith("Try "), err
        lines = lines[2:]
    assert len(lines) == 1, err
    line = lines[0]
    assert not any(ord(c) < 32 or 0x7F <= ord(c) <= 0x9F for c in line), repr(line)
    assert not any(0xD800 <= ord(c) <= 0xDFFF for c in line), repr(line)
    assert "\u202e" not in line and "\u2028" not in line
    return line


@pytest.mark.parametrize("kind", sorted(NAMES))
@pytest.mark.parametrize(
    "command",
    [
        ["replay", "{missing}", "-o", "{tmp}/o.ndjson"],
        ["replay", "{csv}", "--calibration", "{missing}", "-o", "{tmp}/o.ndjson"],
        ["replay", "{csv}", "--profile", "{missing}.toml", "-o", "{tmp}/o.ndjson"],
        ["run", "--port", NO_BOARD, "--background", "{missing}"],
        ["recover", "{missing}", "-o", "{tmp}/o.mcap"],
        ["calibrate", "--positions", "{missing}", "--port", NO_BOARD],
    ],
    ids=["replay-input", "calibration", "profile", "run-background", "recover", "positions"],
)
def test_odd_names_are_shown_escaped_on_one_line(cli, csv_folder, tmp_path, kind, command):
    raw, shown = NAMES[kind]
    missing = str(tmp_path / raw)
    args = [a.format(missing=missing, tmp=tmp_path, csv=csv_folder[0]) for a in command]
    ran = cli(*args)
    assert ran.status == 2, ran
    line = _clean_line(ran.err)
    if kind == "not-utf8" and line.startswith("Error: Invalid value"):
        shown = "caf\ufffd\ufffd"  # click's own usage check: replacement characters, safe
    assert shown in line, line


@pytest.mark.parametrize("kind", ["newline", "escape-sequence", "not-utf8"])
def test_an_existing_output_with_an_odd_name(cli, csv_folder, tmp_path, kind):
    raw, shown = NAMES[kind]
    out = tmp_path / (raw + ".ndjson")
    out.write_text("keep\n")
    ran = cli("replay", csv_folder[0], "-o", out)
    assert ran.status == 2 and shown in _clean_line(ran.err)
    assert out.read_text() == "keep\n"


def test_an_odd_name_replays_fine(cli, csv_folder, tmp_path):
    """Escaping is for messages only: the file itself is written under its own name."""
    out = tmp_path / os.fsdecode(b"out\xff\n.ndjson")
    ran = cli("replay", csv_folder[0], "--association", "geometric", "-o", out)
    assert ran.status == 0 and out.read_text().count("\n") == 3


def test_escape_keeps_printable_text():
    text = "Zürich ünïcødé 日本 emoji 🙂 spaces and 'quotes'"
    assert escape(text) == text
    assert shorten("x" * 10) == "x" * 10


def test_escape_of_bytes_and_surrogates():
    assert escape(b"a\xffb") == "a\\xffb"
    assert escape("\udcff") == "\\xff"
    assert escape("\ud800") == "\\ud800"


@pytest.mark.parametrize(
    "setup",
    ["string-npy", "structured-npy", "empty-labels", "nan-unused-field"],
)
def test_no_internal_error_for_odd_contents(cli, tmp_path, csv_folder, setup):
    if setup == "string-npy":
        np.save(tmp_path / "bg.npy", np.array(["a"]))
        ran = cli("run", "--port", NO_BOARD, "--background", tmp_path / "bg.npy")
        assert ran.status == 2 and "not numbers" in ran.err
    elif setup == "structured-npy":
        np.save(tmp_path / "bg.npy", np.zeros(2, dtype=[("a", "f4")]))
        ran = cli("run", "--port", NO_BOARD, "--background", tmp_path / "bg.npy")
        assert ran.status == 2 and "not numbers" in ran.err
    elif setup == "empty-labels":
        folder = tmp_path / "rec"
        folder.mkdir()
        for src in csv_folder[0].glob("*_frames.csv"):
            (folder / src.name).write_bytes(src.read_bytes())
            (folder / src.name.replace("_frames", "_labels")).write_text("")
        ran = cli("replay", folder, "--association", "geometric", "-o", tmp_path / "o.ndjson")
        assert ran.status in (0, 1) and "Warning" not in ran.err and "loadtxt" not in ran.err
    else:
        cal = tmp_path / "cal.toml"
        cal.write_text("[acquisition]\ncarrier_hz = nan\n")
        ran = cli("replay", csv_folder[0], "--calibration", cal, "-o", tmp_path / "o.ndjson")
        assert ran.status == 2 and "acquisition.carrier_hz" in ran.err
    assert "internal error" not in ran.err


def test_a_library_warning_becomes_one_log_line(cli, monkeypatch):
    import warnings

    from spiel_edge.cli import profile as profile_cli

    listing = profile_cli.command.commands["list"]
    original = listing.callback

    def noisy(*args, **kwargs):
        warnings.warn("a library's\nmultiline warning", UserWarning, stacklevel=1)
        return original(*args, **kwargs)

    monkeypatch.setattr(listing, "callback", noisy)
    ran = cli("profile", "list")
    assert ran.status == 0
    lines = [line for line in ran.err.splitlines() if "UserWarning" in line]
    assert len(lines) == 1 and "multiline warning" in lines[0], ran.err


def test_closed_stdout_is_one_line_not_a_crash(tmp_path):
    proc = subprocess.run(
        [*CLI, "profile", "show", "spiel-icra23"],
        stdout=None,
        stderr=subprocess.PIPE,
        timeout=120,
        check=False,
        preexec_fn=lambda: os.close(1),
    )
    err = proc.stderr.decode()
    assert proc.returncode == 2 and "stdout is closed" in err, err
    assert "Traceback" not in err and "internal error" not in err


def test_closed_stdout_does_not_matter_when_unused(tmp_path, csv_folder):
    out = tmp_path / "o.ndjson"
    proc = subprocess.run(
        [*CLI, "replay", str(csv_folder[0]), "--association", "geometric", "-o", str(out)],
        stderr=subprocess.PIPE,
        timeout=300,
        check=False,
        preexec_fn=lambda: os.close(1),
    )
    assert proc.returncode == 0, proc.stderr.decode()
    assert out.read_text().count("\n") == 3


def test_closed_stderr_keeps_the_status(tmp_path):
    proc = subprocess.run(
        [*CLI, "replay", str(tmp_path / "missing.mcap")],
        stdout=subprocess.PIPE,
        timeout=120,
        check=False,
        preexec_fn=lambda: os.close(2),
    )
    assert proc.returncode == 2


def test_numba_without_a_writable_cache_is_our_message(cli, monkeypatch):
    """numba's own error (its exact words) when neither the source tree nor NUMBA_CACHE_DIR
    can be written: one line saying what to set, not `internal error`."""
    from spiel_edge.cli import profile as profile_cli

    listing = profile_cli.command.commands["list"]

    def no_cache(*args, **kwargs):
        raise RuntimeError(
            "cannot cache function 'kernel': no locator available for file '/usr/lib/x.py'"
        )

    monkeypatch.setattr(listing, "callback", no_cache)
    ran = cli("profile", "list")
    assert ran.status == 2 and "NUMBA_CACHE_DIR" in _clean_line(ran.err), ran
