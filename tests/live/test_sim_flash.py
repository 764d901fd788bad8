"""The virtual board's two-slot config flash: an interrupted commit never loses the old config."""

from __future__ import annotations

import time

import pytest
from crc32c import crc32c

from spiel_edge.device import DeviceSession
from spiel_edge.errors import DeviceDisconnectedError
from spiel_edge.protocol import (
    ConfigCommit,
    ConfigCommitResponse,
    ConfigRead,
    ConfigSource,
    ConfigStatus,
    ConfigStatusRequest,
    ConfigWrite,
    ErrorCode,
    ErrorResponse,
    FrameDecoder,
    StreamStart,
    decode_message,
    encode_message,
)
from spiel_edge.sim import Flash, PowerCut
from spiel_edge.sim.board import VirtualBoard
from spiel_edge.sim.protocol_sim import device_for_url
from spiel_edge.sim.scenes import ReplayScene

OLD = b"old config " * 30
NEW = b"the new configuration " * 40


def committed(cut_at: int) -> tuple[Flash, bool]:
    flash = Flash()
    flash.commit(OLD)
    flash.cut_at = flash.ops + cut_at
    try:
        flash.commit(NEW)
    except PowerCut:
        return flash, True
    return flash, False


def test_power_cut_at_every_flash_operation_keeps_one_whole_config():
    reference = Flash()
    reference.commit(OLD)
    before = reference.ops
    reference.commit(NEW)
    n_ops = reference.ops - before
    assert n_ops >= 4  # erase, data pages, header
    for k in range(n_ops + 1):
        flash, cut = committed(k)
        assert cut == (k < n_ops)
        assert flash.read_active() == (OLD if cut else NEW)
        if not cut:
            continue
        flash.commit(NEW)  # and the next attempt succeeds
        assert flash.read_active() == NEW


def test_generations_alternate_slots():
    flash = Flash()
    infos = [flash.commit(bytes([i]) * 10) for i in range(4)]
    assert [i.slot for i in infos] == [0, 1, 0, 1]
    assert [i.generation for i in infos] == [1, 2, 3, 4]
    assert flash.read_active() == bytes([3]) * 10


def ask(board: VirtualBoard, msg, seq: int):
    out = board.receive(encode_message(msg, seq=seq), 0.0)
    [frame] = FrameDecoder().feed(b"".join(o.wire for o in out))
    return decode_message(frame)


def test_config_messages_stage_verify_and_commit():
    board = VirtualBoard(ReplayScene())
    assert ask(board, ConfigRead(0, 10), 1).code == ErrorCode.NOT_FOUND
    assert ask(board, ConfigWrite(0, NEW[:300]), 2).staged_length == 300
    assert ask(board, ConfigWrite(300, NEW[300:]), 3).staged_length == len(NEW)
    assert ask(board, ConfigWrite(5000, b"x"), 4).code == ErrorCode.TOO_LARGE
    assert ask(board, ConfigRead(0, 50, ConfigSource.STAGING), 5).data == NEW[:50]
    assert ask(board, ConfigCommit(len(NEW), crc32c(NEW) ^ 1), 6).code == ErrorCode.CORRUPT
    done = ask(board, ConfigCommit(len(NEW), crc32c(NEW)), 7)
    assert isinstance(done, ConfigCommitResponse) and (done.slot, done.generation) == (0, 1)
    assert ask(board, ConfigRead(10, 20), 8).data == NEW[10:30]
    assert ask(board, ConfigRead(len(NEW) + 5, 20), 12).data == b""  # empty past the end
    status = ask(board, ConfigStatusRequest(), 9)
    assert isinstance(status, ConfigStatus) and status.active_slot == 0 and status.slot0_valid == 1
    assert status.staged_length == 0  # a commit clears the staging
    ask(board, StreamStart(rate_hz=10), 10)
    busy = ask(board, ConfigCommit(len(NEW), crc32c(NEW)), 11)
    assert isinstance(busy, ErrorResponse) and busy.code == ErrorCode.BAD_STATE


def test_power_cut_during_commit_unplugs_the_board_and_keeps_the_old_config(sim_url):
    url = sim_url("unplug_ms=50")
    device = device_for_url(url)
    device.board.flash.commit(OLD)
    device.board.flash.cut_at = device.board.flash.ops + 2  # during the data pages
    with DeviceSession(url, reconnect=False) as session:
        session.request(ConfigWrite(0, NEW))
        with pytest.raises(DeviceDisconnectedError):
            session.request(ConfigCommit(len(NEW), crc32c(NEW)))
    assert device.power_cuts == 1
    time.sleep(0.06)  # the board comes back with the old config active
    with DeviceSession(url, reconnect=False) as session:
        assert session.request(ConfigRead(0, len(OLD))).data == OLD


def test_session_config_transfer_and_a_power_cut_at_every_flash_operation(sim_url):
    url = sim_url("unplug_ms=20&max_payload=1030")  # chunks of max_payload - 6 bytes
    device = device_for_url(url)
    blob = bytes(range(256)) * 15  # four CONFIG_WRITE chunks
    with DeviceSession(url, reconnect=False) as session:
        sent = []
        session.write_config(OLD)
        session.commit_config(crc32c(OLD))
        session.write_config(blob, progress=sent.append)
        assert sent == [1024, 1024, 1024, 768] and session.read_config(ConfigSource.STAGING) == blob
        ops_before = device.board.flash.ops
    n_ops = 2 + len(blob) // 256  # erase, pages, header
    for k in range(n_ops):
        device.board.flash.cut_at = device.board.flash.ops + k
        time.sleep(0.025)  # any earlier cut has healed
        with DeviceSession(url, reconnect=False) as session:
            session.write_config(blob)
            with pytest.raises(DeviceDisconnectedError):
                session.commit_config(crc32c(blob))
        time.sleep(0.025)
        with DeviceSession(url, reconnect=False) as session:
            assert session.read_config() == OLD
            assert session.config_status().staged_length == 0  # RAM lost with the power
    assert (
        device.power_cuts == n_ops
        and device.board.flash.ops - ops_before == n_ops * (n_ops - 1) // 2
    )
    with DeviceSession(url, reconnect=False) as session:
        session.write_config(blob)
        done = session.commit_config(crc32c(blob))
        assert session.read_config() == blob and done.generation == 2
