"""Fixtures of the C reference firmware tests: builds (once per session), the scans file of
the vendored recordings, and a posix board on a pty. These tests always run: they need only
the system C compiler and make (no dataset, no other Debian package)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.firmware.firmware import PosixBoard, build_driver, build_posix
from tools.release.firmware_scans import write_scans

SAMPLE_RATE_HZ = 22000


@pytest.fixture(scope="session")
def fw_build(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fw-build")


@pytest.fixture(scope="session")
def posix_exe(fw_build) -> Path:
    return build_posix(fw_build)


@pytest.fixture(scope="session")
def driver_exe(fw_build) -> Path:
    return build_driver(fw_build, SPIEL_MAX_PAYLOAD=8256, SPIEL_FW_UPDATE=1)


@pytest.fixture(scope="session")
def subset_scans(tmp_path_factory, subset) -> Path:
    """The vendored subset in recorded order, as the virtual board's replay scene streams it."""
    return write_scans(tmp_path_factory.mktemp("scans") / "subset.spas", subset.frames, 22000)


@pytest.fixture
def posix_board(posix_exe, subset_scans, tmp_path):
    """``posix_board(*extra, exe=..., scans=..., flash=...)`` -> a started PosixBoard."""
    made: list[PosixBoard] = []

    def make(*extra: str, exe: Path | None = None, scans: Path | None = None, flash=None):
        board = PosixBoard(
            exe or posix_exe,
            scans or subset_scans,
            flash or tmp_path / "flash.bin",
            *extra,
        )
        made.append(board.start())
        return board

    yield make
    for board in made:
        board.stop()


def frames_of(scans: Path) -> np.ndarray:
    """The acquisitions of a scans file (acquisitions, channels, samples) uint16."""
    raw = Path(scans).read_bytes()
    n_ch, n_s = int.from_bytes(raw[6:8], "little"), int.from_bytes(raw[8:10], "little")
    return np.frombuffer(raw[20:], "<u2").reshape(-1, n_ch, n_s)


@pytest.fixture(autouse=True)
def _emulated_boards_answer_slowly(request, monkeypatch):
    """An emulated board (QEMU, rp2040js) on a loaded machine answers seconds late at times
    (rp2040js at load 12-15 missed 4 tries of 0.5 s): its tests give every request 4 times the
    time (SPIEL_REQUEST_TIMEOUT_SCALE, inherited by the CLI processes they start)."""
    if request.module.__name__.rsplit(".", 1)[-1].startswith(("test_qemu", "test_rp2040")):
        monkeypatch.setenv("SPIEL_REQUEST_TIMEOUT_SCALE", "4")
