"""Protocol version 2, pure parts: images, the clock estimator, telemetry, the I/Q kernel."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from spiel_edge.device.iq import iq_envelope, iq_envelope_reference
from spiel_edge.device.telemetry import BoardTelemetry
from spiel_edge.device.timesync import TimeSyncEstimator
from spiel_edge.errors import InputError
from spiel_edge.protocol.image import (
    IMAGE_HEADER_SIZE,
    ImageError,
    check_body,
    pack_image,
    parse_image,
)
from spiel_edge.protocol.link_messages import Heartbeat, LogMessage

BODY = bytes(range(256)) * 5


def test_image_round_trip_and_every_damage_is_named() -> None:
    image = pack_image(BODY, version="1.2.3", target="posix", min_protocol=1, max_protocol=2)
    header = parse_image(image)
    assert (header.version, header.target, header.body_size) == ("1.2.3", "posix", len(BODY))
    assert header.image_size == len(image) == IMAGE_HEADER_SIZE + len(BODY)
    with pytest.raises(ImageError, match="truncated"):
        parse_image(image[:-1])
    with pytest.raises(ImageError, match="after its declared end"):
        parse_image(image + b"\x00")
    flipped = bytearray(image)
    flipped[IMAGE_HEADER_SIZE + 7] ^= 1
    with pytest.raises(ImageError, match="corrupt"):
        parse_image(bytes(flipped))
    head = bytearray(image)
    head[10] ^= 1  # the version text: the header CRC catches it
    with pytest.raises(ImageError, match="header is corrupt"):
        parse_image(bytes(head))
    with pytest.raises(ImageError, match="magic"):
        parse_image(b"ELF!" + image[4:])
    with pytest.raises(ImageError):
        pack_image(BODY, version="x" * 17, target="posix")


def test_an_mps2_body_is_a_flat_binary_with_its_vector_table() -> None:
    import struct

    app = struct.pack("<II", 0x2000_4000, 0x0001_0101) + bytes(0x200)
    check_body(app, "mps2-an386")
    check_body(b"\x7fELF anything", "posix")  # other targets are not checked
    with pytest.raises(ImageError, match="app.bin"):
        check_body(b"\x7fELF" + app, "mps2-an386")
    with pytest.raises(ImageError, match="too short"):
        check_body(app[:6], "mps2-an386")
    for sp, pc in ((0x2000_4000, 0x0000_0101), (0x2000_4000, 0x0001_0100), (0x0, 0x0001_0101)):
        with pytest.raises(ImageError, match="not a mps2-an386 application"):
            check_body(struct.pack("<II", sp, pc) + app[8:], "mps2-an386")


def exchanges(est, offset_us, rate, times_s, rtt_us=200.0, boot=1):
    """Exact exchanges: the board reads its clock at the midpoint of each round trip."""
    for t in times_s:
        mid = t * 1e6
        board = (mid - offset_us) / rate
        est.add(mid - rtt_us / 2, mid + rtt_us / 2, board, boot)


def test_estimator_recovers_offset_and_drift_from_clean_exchanges() -> None:
    est = TimeSyncEstimator()
    rate = 1 - 200e-6
    exchanges(est, 5e6, rate, np.arange(0, 60, 0.25))
    board = (70e6 - 5e6) / rate  # 10 s past the last exchange
    host, u = est.map(board)
    # exact value; the stated uncertainty is the range of every line that fits every exchange
    # (the hulls of the sends and reads, 10 s beyond the window: about 140 us)
    assert abs(host - 70e6) < 5 and 100 < u < 250


def _jittered(rng, *, seconds: float):
    """Exchanges every 0.25 s with up to 1 ms of delay on each leg, a board 200 ppm fast and
    7 s behind: (the estimator, rate, offset)."""
    est = TimeSyncEstimator()
    rate, offset = 1 + 200e-6, 7e6
    for t in np.arange(0, seconds, 0.25):
        up, down = rng.uniform(0, 1000, 2)
        stamp = t * 1e6 + up
        est.add(t * 1e6, stamp + down, (stamp - offset) / rate, 1)
    return est, rate, offset


def test_jittered_exchanges_give_the_corridor_centre_far_inside_the_jitter() -> None:
    """1 ms of jitter on each leg: the lines above every send and below every read pin the
    clock to a few us, where a line through the midpoints keeps their spread (~100 us)."""
    rng = np.random.default_rng(3)
    est, rate, offset = _jittered(rng, seconds=120)
    truth = 125e6
    host, u = est.map((truth - offset) / rate)
    assert abs(host - truth) < 15 and abs(host - truth) <= u < 200


def test_single_exchange_states_its_hard_bound() -> None:
    est = TimeSyncEstimator()
    est.add(1000.0, 3000.0, 50.0, 7)  # round trip 2 ms: +-1 ms
    host, u = est.map(50.0)
    assert host == 2000.0 and u == pytest.approx(1002.0)


def test_answers_months_off_or_backwards_are_dropped_then_a_step_is_followed() -> None:
    est = TimeSyncEstimator()
    exchanges(est, 0.0, 1.0, np.arange(0, 10, 0.25))
    months = 90 * 86400e6
    assert not est.add(10.25e6 - 100, 10.25e6 + 100, 10.25e6 + months, 1)
    assert not est.add(10.5e6 - 100, 10.5e6 + 100, 10.5e6 - 5e6, 1)  # backwards
    assert est.counters.outliers + est.counters.backwards == 2
    assert all("ignored" in m for m in est.take_messages())
    host, _ = est.map(11e6)
    assert abs(host - 11e6) < 10  # the estimate was not moved
    # the board's clock really was stepped: five agreeing answers restart the estimate
    for k in range(5):
        t = 12e6 + k * 0.25e6
        est.add(t - 100, t + 100, t + 3e9, 1)
    assert est.counters.steps == 1
    host, _ = est.map(13.5e6 + 3e9)
    assert abs(host - 13.5e6) < 200


def test_reset_restarts_the_offset_and_keeps_the_drift() -> None:
    est = TimeSyncEstimator()
    rate = 1 + 150e-6
    exchanges(est, 0.0, rate, np.arange(0, 120, 0.25), rtt_us=100.0)
    est.add(200e6 - 50, 200e6 + 50, 0.0, 2)  # new boot id: its clock restarted at 0
    assert est.counters.resets == 1
    host, u = est.map(1e6)  # 1 s of board time later
    assert abs(host - (200e6 + rate * 1e6)) < 60 and u < 500


def test_telemetry_rate_limits_board_logs_and_reports_unknown_flags(caplog) -> None:
    tel = BoardTelemetry("board X", rate_per_s=20, burst=40)
    with caplog.at_level(logging.INFO, logger="spiel_edge.board_config"):
        for i in range(1000):  # 1000 lines within 1 s
            tel.log_line(LogMessage(4, 0, 0, f"line {i}\x1b[31m" + "x" * 500), now=i / 1000)
        tel.summarise(1.0, force=True)
        tel.heartbeat(Heartbeat(1, 0, 0, 500, 0x8000_0000 | 0x02, 1, 0), now=1.0)
    forwarded = [r for r in caplog.records if "line " in r.getMessage()]
    assert 40 <= len(forwarded) <= 61  # the burst plus 20 per second
    assert tel.counters.board_logs == 1000
    assert tel.counters.board_logs_suppressed == 1000 - len(forwarded)
    assert all(len(r.getMessage()) < 260 and "\x1b" not in r.getMessage() for r in forwarded)
    text = caplog.text
    assert "not shown" in text and "unknown error flags 0x80000000" in text and "overrun" in text
    assert tel.counters.unknown_flags == 1


def test_heartbeat_silence_is_noticed_after_three_periods() -> None:
    tel = BoardTelemetry("board X")
    tel.expect(500, now=0.0)
    assert tel.silent_for(1.5) is None
    assert tel.silent_for(1.8) == pytest.approx(1.8)
    tel.heartbeat(Heartbeat(1, 1, 0, 500, 0, 1, 0), now=1.8)
    assert tel.silent_for(2.0) is None


def test_iq_kernel_matches_numpy() -> None:
    rng = np.random.default_rng(0)
    pairs = rng.integers(-32768, 32768, size=(4, 128), dtype=np.int16)
    env, phase = iq_envelope(pairs)
    ref_env, ref_phase = iq_envelope_reference(pairs)
    np.testing.assert_allclose(env, ref_env, rtol=1e-12)
    np.testing.assert_allclose(phase, ref_phase, atol=1e-6)
    with pytest.raises(InputError):
        iq_envelope(pairs[:, :3])
    with pytest.raises(InputError):
        iq_envelope(pairs.astype(np.int32))


# --- TIME_SYNC's drop rules, the bound, the fit and the schedule (PROTOCOL.md § 14.1) ----------


def test_answers_with_an_impossible_or_too_long_round_trip_are_dropped() -> None:
    est = TimeSyncEstimator()
    assert not est.add(1000.0, 900.0, 50.0, 1)  # read before it was sent
    assert not est.add(0.0, 250_000.0, 50.0, 1)  # 250 ms: longer than 200 ms tells nothing
    assert not est.add(0.0, 200.0, float("nan"), 1)
    assert est.counters.long_rtt == 2 and est.counters.absurd == 1
    assert est.counters.used == 0 and est.map(50.0) is None
    assert est.add(0.0, 200_000.0, 50.0, 1)  # 200 ms is still taken


def test_backwards_only_beyond_what_the_round_trips_allow() -> None:
    est = TimeSyncEstimator()
    assert est.add(10e6 - 100, 10e6 + 100, 5_000_100.0, 1)
    # 100 us before the previous answer's board time: both were read somewhere inside their
    # 200 us round trips, so this is not backwards
    assert est.add(10e6 + 100, 10e6 + 300, 5_000_000.0, 1)
    assert est.counters.backwards == 0
    assert not est.add(10e6 + 300, 10e6 + 500, 5_000_000.0 - 401.0, 1)  # beyond: backwards
    assert est.counters.backwards == 1


def test_an_answer_more_than_2_ms_off_the_line_is_an_outlier() -> None:
    """Off by more than max(8 uncertainties, 2 ms) (plus half its round trip): dropped."""
    for off_us, kept in ((1500.0, True), (5000.0, False)):
        est = TimeSyncEstimator()
        exchanges(est, 0.0, 1.0, np.arange(0, 10, 0.25), rtt_us=60.0)
        _, u = est.map(10.25e6)
        assert 8 * u < 2000  # the 2 ms floor is the threshold here
        t = 10.25e6
        assert est.add(t - 100, t + 100, t + off_us, 1) is kept
        assert est.counters.outliers == (0 if kept else 1)


def test_five_agreeing_outliers_are_a_step_and_the_fit_restarts_from_them() -> None:
    est = TimeSyncEstimator()
    exchanges(est, 0.0, 1.0, np.arange(0, 10, 0.25))
    for k in range(4):
        t = 12e6 + k * 0.25e6
        assert not est.add(t - 100, t + 100, t + 3e9, 1)
    assert est.counters.steps == 0 and est.counters.outliers == 4  # four are not enough
    t = 13e6
    assert est.add(t - 100, t + 100, t + 3e9, 1)  # the fifth: a step
    assert est.counters.steps == 1
    assert not est.estimate.fitted  # five exchanges: the best one's bound
    for k in range(1, 4):  # three more: eight since the step, the five kept among them
        t = 13e6 + k * 0.25e6
        assert est.add(t - 100, t + 100, t + 3e9, 1)
    assert est.estimate.fitted


def test_the_bound_is_the_shortest_round_trips_until_eight_exchanges() -> None:
    est = TimeSyncEstimator()
    est.add(0.0, 2000.0, 1000.0, 1)  # 2 ms round trip
    est.add(1e6, 1e6 + 200.0, 1e6 + 100.0, 1)  # 200 us: the best
    host, u = est.map(1e6 + 100.0)
    assert host == pytest.approx(1e6 + 100.0) and u == pytest.approx(100.0 + 2.0)
    # one second of board time later: plus the 3 % drift bound (RC oscillators) over it
    assert est.map(2e6 + 100.0)[1] == pytest.approx(102.0 + 30000.0)
    for k in range(2, 7):
        est.add(k * 1e6, k * 1e6 + 200.0, k * 1e6 + 100.0, 1)
    assert est.counters.used == 7 and not est.estimate.fitted
    est.add(7e6, 7e6 + 200.0, 7e6 + 100.0, 1)
    assert est.estimate.fitted  # 8 exchanges: the line


def test_unmap_inverts_map_on_a_drifting_clock() -> None:
    est = TimeSyncEstimator()
    rate = 1 - 200e-6
    exchanges(est, 5e6, rate, np.arange(0, 60, 0.25))
    board = (70e6 - 5e6) / rate
    host, _ = est.map(board)
    assert est.unmap(host) == pytest.approx(board, abs=1.0)
    assert est.unmap(70e6) == pytest.approx(board, abs=10.0)  # the board time of host 70 s
    assert TimeSyncEstimator().unmap(1.0) is None


def test_sync_is_fast_until_64_exchanges_and_messages_are_taken_once() -> None:
    est = TimeSyncEstimator()
    assert est.interval(0.25) == pytest.approx(0.1) and est.interval(0.05) == 0.05
    exchanges(est, 0.0, 1.0, np.arange(0, 63 * 0.25, 0.25))
    assert est.counters.used == 63 and est.interval(0.25) == pytest.approx(0.1)
    exchanges(est, 0.0, 1.0, [63 * 0.25])
    assert est.interval(0.25) == 0.25  # 64 in hand: the normal period
    assert not est.add(0.0, 250_000.0, 1.0, 1)
    est.add(20e6, 20e6 + 200.0, 20e6 + 100.0, 2)  # a new boot id
    assert len(est.take_messages()) == 1 and est.take_messages() == []


@pytest.mark.parametrize("seed", range(8))
def test_far_beyond_a_short_window_the_uncertainty_still_covers_the_truth(seed) -> None:
    """10 s of exchanges with 1 ms of jitter on each leg, mapped 90 s past them: the rate is
    known only to the corridor's range of rates, and the stated uncertainty grows with the
    larger side of that range (the rate may be off either way)."""
    rng = np.random.default_rng(seed)
    est, rate, offset = _jittered(rng, seconds=10)
    truth = 100e6
    host, u = est.map((truth - offset) / rate)
    assert abs(host - truth) <= u


def test_every_error_flag_the_protocol_names_is_known() -> None:
    """PROTOCOL.md § 14.2: FLASH 0x01 ... LOG_DROPPED 0x40; only other bits are unknown."""
    tel = BoardTelemetry("board X")
    tel.heartbeat(Heartbeat(1, 0, 0, 500, 0x7F, 1, 0), now=1.0)
    assert tel.counters.unknown_flags == 0
    tel.heartbeat(Heartbeat(2, 0, 0, 500, 0x80, 1, 0), now=1.5)
    assert tel.counters.unknown_flags == 1


# --- images: the header's checks and the protocol range (PROTOCOL.md § 14.3) -------------------


def _reheadered(image: bytes, **changes) -> bytes:
    """``image`` with header fields changed and its header CRC made right again (a well-formed
    header that says something else)."""
    from crc32c import crc32c

    from spiel_edge.protocol.image import IMAGE_HEADER, IMAGE_HEADER_FIELDS

    names = [name for name, _, _ in IMAGE_HEADER_FIELDS]
    values = dict(zip(names, IMAGE_HEADER.unpack_from(image), strict=True))
    values.update(changes)
    head = IMAGE_HEADER.pack(*(values[n] for n in names))[:-4]
    return head + crc32c(head).to_bytes(4, "little") + image[IMAGE_HEADER_SIZE:]


def test_a_well_formed_header_that_says_the_wrong_thing_is_refused() -> None:
    image = pack_image(BODY, version="1.2.3", target="posix")
    assert parse_image(_reheadered(image)).version == "1.2.3"  # the helper changes nothing
    for changes, words in (
        ({"header_version": 2}, "header version 2 size 96 is not supported"),
        ({"header_size": 128}, "size 128 is not supported"),
        ({"min_protocol": 0}, "empty protocol range 0-2"),
        ({"min_protocol": 3}, "empty protocol range 3-2"),
        ({"body_sha256": bytes(32)}, "SHA-256 mismatch"),  # the CRC-32C still matches
    ):
        with pytest.raises(ImageError, match=words):
            parse_image(_reheadered(image, **changes))
    flipped = bytearray(image)
    flipped[IMAGE_HEADER_SIZE + 7] ^= 1
    with pytest.raises(ImageError, match="CRC-32C mismatch"):  # caught by the cheaper check
        parse_image(bytes(flipped))
    with pytest.raises(ImageError, match="shorter than the 96-byte header"):
        parse_image(image[:50])


def test_pack_image_refuses_what_the_header_cannot_say() -> None:
    assert parse_image(pack_image(BODY, version="v" * 16, target="mps2-an386")).version == "v" * 16
    for kw in (
        {"version": "1.0\x00rc"},
        {"version": ""},
        {"target": "t" * 17},
        {"min_protocol": 0},
        {"min_protocol": 3, "max_protocol": 2},
        {"max_protocol": 256},
    ):
        args = {"version": "1.0", "target": "posix", **kw}
        with pytest.raises(ImageError):
            pack_image(BODY, **args)


def test_an_image_speaks_a_range_that_shares_a_version() -> None:
    header = parse_image(
        pack_image(BODY, version="1", target="posix", min_protocol=2, max_protocol=3)
    )
    assert header.speaks(1, 2) and header.speaks(3, 4) and header.speaks(1, 5)
    assert not header.speaks(1, 1) and not header.speaks(4, 5)


def test_an_mps2_stack_may_start_at_the_top_of_ram_and_the_reset_handler_is_in_the_body() -> None:
    import struct

    body = bytes(0x200)
    top = struct.pack("<II", 0x2020_0000, 0x0001_0101)  # SP = end of RAM, as linkers put it
    check_body(top + body[8:], "mps2-an386")
    beyond = struct.pack("<II", 0x2000_4000, 0x0001_0000 + 0x201)  # past the body's end
    with pytest.raises(ImageError, match="not a mps2-an386 application"):
        check_body(beyond + body[8:], "mps2-an386")
