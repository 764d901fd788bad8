"""Power cuts and flash failures during a config commit on the posix C firmware: SIGKILL in
the middle of every flash operation of the commit (the firmware kills itself there, half the
operation done), then a restart on the same flash file: the board always comes back with the
old or the new config, never neither. A flash write that fails: the error code, the old
config active, the board still working."""

from __future__ import annotations

import pytest
from crc32c import crc32c

from spiel_edge.device import DeviceSession
from spiel_edge.errors import DeviceDisconnectedError, DeviceError, DeviceRequestError
from spiel_edge.protocol import ConfigCommit, ConfigRead, ConfigSource, ConfigWrite, ErrorCode

OLD = b"SPCF old config " * 20  # opaque to the board: any bytes are stored as they are
NEW = b"SPCF the new one " * 30  # 510 bytes: erase, two pages, metadata = 4 operations
N_OPS = 1 + (len(NEW) + 255) // 256 + 1


def active(port) -> bytes | None:
    with DeviceSession(port, reconnect=False) as session:
        try:
            return session.read_config(ConfigSource.ACTIVE)
        except DeviceRequestError as exc:
            assert exc.code == ErrorCode.NOT_FOUND
            return None


def commit(port, blob: bytes):
    with DeviceSession(port, reconnect=False) as session:
        session.write_config(blob)
        return session.request(ConfigCommit(len(blob), crc32c(blob)), retries=0)


@pytest.fixture
def old_flash(posix_board, tmp_path):
    """A flash file holding OLD as its committed config (generation 1 in slot 0)."""
    flash = tmp_path / "old.bin"
    board = posix_board(flash=flash)
    commit(board.port, OLD)
    board.stop()
    return flash.read_bytes()


@pytest.mark.parametrize("cut", range(N_OPS + 1))
def test_a_power_cut_at_every_flash_operation_keeps_old_or_new(
    posix_board, tmp_path, old_flash, cut
):
    flash = tmp_path / f"cut{cut}.bin"
    flash.write_bytes(old_flash)
    board = posix_board("--flash-cut", str(cut), flash=flash)
    if cut < N_OPS:
        with pytest.raises((DeviceDisconnectedError, DeviceError)):
            commit(board.port, NEW)
        assert board.wait_dead() == -9  # SIGKILL: the power went
    else:
        commit(board.port, NEW)  # past the last operation: the commit completes
        board.stop()
    after = posix_board(flash=flash)  # power on again
    got = active(after.port)
    assert got in (OLD, NEW), f"cut at operation {cut}: neither config survived"
    if cut < N_OPS - 1:  # before the metadata write: the old one
        assert got == OLD
    elif cut == N_OPS:
        assert got == NEW


@pytest.mark.parametrize("fail", range(N_OPS))
def test_a_failed_flash_write_answers_an_error_and_keeps_the_old_config(
    posix_board, tmp_path, old_flash, fail
):
    flash = tmp_path / f"fail{fail}.bin"
    flash.write_bytes(old_flash)
    board = posix_board("--flash-fail", str(fail), flash=flash)
    with pytest.raises(DeviceRequestError) as caught:
        commit(board.port, NEW)
    assert caught.value.code == ErrorCode.FLASH_WRITE_FAILED
    assert active(board.port) == OLD  # the same boot goes on with the old config
    with DeviceSession(board.port, reconnect=False) as session:
        assert session.read_config(ConfigSource.STAGING) == NEW  # staging kept for a retry
        answer = session.request(ConfigCommit(len(NEW), crc32c(NEW)))  # the flash works again
        assert answer.length == len(NEW)
        assert session.request(ConfigRead(0, 16, ConfigSource.ACTIVE)).data == NEW[:16]


def test_a_host_that_dies_mid_commit_leaves_the_old_config(posix_board, tmp_path, old_flash):
    """The host writes half the staging and vanishes: nothing is committed."""
    flash = tmp_path / "host.bin"
    flash.write_bytes(old_flash)
    board = posix_board(flash=flash)
    with DeviceSession(board.port, reconnect=False) as session:
        session.request(ConfigWrite(0, NEW[:200]))
    with DeviceSession(board.port, reconnect=False) as session:
        with pytest.raises(DeviceRequestError) as caught:  # a later host commits too much
            session.request(ConfigCommit(len(NEW), crc32c(NEW)))
        assert caught.value.code == ErrorCode.INVALID
    assert active(board.port) == OLD
