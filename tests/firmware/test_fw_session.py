"""The posix C firmware on a pty against the host's device session: handshake, versions,
streaming of the recordings in order, counters of the run's own stream."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from spiel_edge.device import DeviceSession
from tests.firmware.conftest import frames_of
from tests.protocol_v2.start_at_check import check_start_at


def take(session, n):
    out = []
    for acq in session.acquisitions(threading.Event()):
        out.append(acq)
        if len(out) == n:
            return out
    return out


def test_handshake_negotiates_version_2_and_streams_the_recordings(posix_board, subset_scans):
    board = posix_board()
    with DeviceSession(board.port, reconnect=False) as session:
        hello = session.hello
        assert (hello.protocol_version, hello.min_version, hello.max_version) == (2, 1, 2)
        assert (hello.n_channels, hello.max_payload, hello.serial) == (4, 1024, "POSIX0001")
        assert session.max_payload == 1024
        answer = session.start_stream(rate_hz=200, n_samples=64)
        assert (answer.n_channels, answer.channel_mask, answer.sample_rate_hz) == (4, 0xF, 22000)
        got = take(session, 10)
        session.stop_stream()
    frames = frames_of(subset_scans)
    # indices increase (one skipped when the shared CPU held the firmware back a whole period
    # is an overrun, which uses its index); the recordings arrive in order all the same
    assert got[0].index == 0 and all(b.index > a.index for a, b in zip(got, got[1:], strict=False))
    for k, acq in enumerate(got):
        np.testing.assert_array_equal(acq.samples, frames[k])


def test_a_channel_subset_keeps_the_physical_channel_ids(posix_board, subset_scans):
    board = posix_board()
    with DeviceSession(board.port, reconnect=False) as session:
        answer = session.start_stream(rate_hz=200, n_samples=64, channel_mask=0b1010)
        assert (answer.n_channels, answer.channel_mask) == (2, 0b1010)
        got = take(session, 3)
        session.stop_stream()
    frames = frames_of(subset_scans)
    for k, acq in enumerate(got):
        np.testing.assert_array_equal(acq.samples, frames[k][[1, 3]])


def test_a_stream_starts_at_a_time_of_the_boards_clock(posix_board):
    """STREAM_START's start_at_us (v2, START_AT): ahead, past (its grid kept), too far."""
    with DeviceSession(posix_board().port, reconnect=False) as session:
        check_start_at(session)


def test_a_version_1_build_keeps_working(posix_board, fw_build, subset_scans):
    from tests.firmware.firmware import build_posix

    board = posix_board(exe=build_posix(fw_build, SPIEL_PROTOCOL_MAX=1))
    with DeviceSession(board.port, reconnect=False) as session:
        assert (session.hello.protocol_version, session.hello.max_version) == (1, 1)
        assert not session.offers_start_at()  # START_AT is version 2's
        answer = session.start_stream(rate_hz=200, n_samples=64)
        assert answer.channel_mask == 0  # absent in version 1
        got = take(session, 4)
        session.stop_stream()
    np.testing.assert_array_equal(got[3].samples, frames_of(subset_scans)[3])


def test_run_counters_count_from_the_streams_own_start(posix_board):
    import time

    board = posix_board()
    with DeviceSession(board.port, reconnect=False) as session:  # an earlier host overruns
        session.start_stream(rate_hz=1000, n_samples=64)
        time.sleep(0.5)  # nobody reads: the pty fills, the board skips acquisitions
        session.stop_stream()
    with DeviceSession(board.port, reconnect=False) as session:  # this run, same boot
        session.start_stream(rate_hz=50, n_samples=64)
        take(session, 3)
        status = session.stream_status()
        counts = session.counts()
        session.stop_stream()
    assert status.overruns > 50  # the board counts since its boot: the first host's skips
    assert counts["acquisitions"] == 3
    # this run's own: what its indices lost (0 unless the shared CPU held the board back)
    assert counts["overruns"] == counts["lost"] < 10


def test_the_host_refuses_a_stream_the_link_cannot_carry(posix_board, fw_build):
    from spiel_edge.errors import DeviceError
    from tests.firmware.firmware import build_posix

    board = posix_board(exe=build_posix(fw_build, SPIEL_MAX_PAYLOAD=64))
    with DeviceSession(board.port, reconnect=False) as session:
        assert session.max_payload == 64
        try:
            session.start_stream(rate_hz=50, n_samples=64)
        except DeviceError as exc:
            assert "152-byte stream frames" in str(exc) and "64" in str(exc)
        else:
            raise AssertionError("a 152-byte frame was asked of a 64-byte link")
        answer = session.start_stream(rate_hz=50, n_samples=20)  # 64 bytes: fits
        assert answer.n_samples == 20
        [acq] = take(session, 1)
        session.stop_stream()
    assert acq.samples.shape == (4, 20)


def test_reboot_re_executes_on_the_same_pty_with_a_new_boot_id(posix_board):
    import time

    from spiel_edge.protocol import Reboot

    board = posix_board()
    with DeviceSession(board.port, reconnect=False) as session:
        first = session.hello.boot_id
        session.request(Reboot(0, 20))
    time.sleep(0.3)
    with DeviceSession(board.port, reconnect=False) as session:
        assert session.hello.boot_id != first and session.hello.serial == "POSIX0001"
    with DeviceSession(board.port, reconnect=False) as session:
        session.request(Reboot(1, 50))  # to the bootloader: the posix target has none
    assert board.wait_dead() == 3


def test_a_firmware_whose_host_stops_reading_does_not_spin(posix_board):
    """Streaming into a pty nobody reads: the firmware waits for room (overruns), it does not
    burn a core."""
    import os
    import time

    board = posix_board()
    with DeviceSession(board.port, reconnect=False) as session:
        session.start_stream(rate_hz=1000, n_samples=64)
        ticks = os.sysconf("SC_CLK_TCK")

        def cpu() -> float:
            stat = Path(f"/proc/{board.proc.pid}/stat").read_text()
            fields = stat.rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / ticks  # utime + stime

        time.sleep(0.5)  # the pty fills up: nobody reads
        before, t0 = cpu(), time.monotonic()
        time.sleep(1.0)
        used = (cpu() - before) / (time.monotonic() - t0)
    assert used < 0.1, f"the firmware used {used:.0%} of a core while blocked"


def test_the_makefile_builds_the_posix_target(tmp_path):
    import shutil
    import subprocess

    import pytest

    from tests.firmware.firmware import FIRMWARE, compiler

    if shutil.which("make") is None:
        pytest.skip("no make: the firmware tests need it (firmware.py builds through the Makefile)")
    done = subprocess.run(
        ["make", "-C", str(FIRMWARE), f"BUILD={tmp_path}", f"CC={compiler()}"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "spiel_fw_posix").is_file()


def _blob(header_size: int, toml_length: int, n_samples: int) -> bytes:
    from spiel_edge.protocol.config_blob import HEADER, MAGIC, VERSION

    return HEADER.pack(
        MAGIC, VERSION, header_size, n_samples, 8, 30, 9, 22000.0, 175000.0, 20.0, 30.0, toml_length
    )


def test_a_blob_whose_lengths_add_up_only_modulo_2_to_the_32_is_not_used(posix_board):
    """PROTOCOL.md 13.1: header_size + toml_length must equal the stored length. A 36-byte
    blob with header_size 100 and toml_length 2^32 - 64 adds up only in u32 (it once did and
    its n_samples was used); the board runs with its factory defaults instead."""
    from crc32c import crc32c

    from spiel_edge.protocol import ConfigCommit, ConfigWrite, StreamStart, StreamStop

    def committed_n_samples(session, blob):
        session.request(ConfigWrite(0, blob))
        session.request(ConfigCommit(len(blob), crc32c(blob)))
        answer = session.request(StreamStart(1, 10.0, 0))  # n_samples 0: the config's
        session.request(StreamStop())
        return answer.n_samples

    with DeviceSession(posix_board().port, reconnect=False) as session:
        assert committed_n_samples(session, _blob(36, 0, 32)) == 32  # a usable blob
        assert committed_n_samples(session, _blob(100, 2**32 - 64, 32)) == 64  # the default


def test_a_board_of_32_channels_streams(posix_board, tmp_path):
    """The posix HAL checked a trigger's mask with mask >> n_channels, a shift by 32 for a
    32-channel scans file (undefined; on x86 a shift by 0), so it refused every acquisition."""
    import time

    from spiel_edge.protocol import StreamStart, StreamStatusRequest
    from tools.release.firmware_scans import write_scans

    frames = np.arange(2 * 32 * 16).reshape(2, 32, 16)
    board = posix_board(scans=write_scans(tmp_path / "wide.spas", frames, 22000))
    with DeviceSession(board.port, reconnect=False) as session:
        assert session.hello.n_channels == 32
        assert session.request(StreamStart(2, 100.0, 0)).n_channels == 32
        deadline = time.monotonic() + 10
        while (status := session.request(StreamStatusRequest())).streaming:
            assert time.monotonic() < deadline
            time.sleep(0.05)
    assert (status.acquisitions_sent, status.frames_sent, status.overruns) == (2, 64, 0)
