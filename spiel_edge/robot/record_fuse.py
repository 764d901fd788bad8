"""Board records fused in the robot's frame: the part of ``spiel-edge fuse`` that does not
depend on where the records come from (Zenoh live, robot/zenoh_fuse.py, or the files a board's
``run -o`` wrote, :func:`read_replay` and :func:`replay`).

A record is ``run``'s JSON (``targets``, ``device_time_us``, ``host_time``, ``stamp_host``
with protocol 2). Time: each board's stamps are mapped to this computer's clock from the
records' arrival (robot/clock.py's lower envelope, which absorbs the network's delay). Each
message is checked whole first (robot/record_check.py): one that is not a usable record, or
whose ``host_time`` is more than a second off this computer's clock, is counted by reason and
dropped, never the board for it; a board whose own messages were all bad BAD_RECORDS_LIMIT
times in a row is reported dropped (a clock to synchronise: chrony or PTP) until its next good
record. Per-board diagnostics ride in every fused record (``boards``).
Odometry (``odom`` tracking) comes as messages (robot/odometry.py: JSON or a ROS 2
nav_msgs/msg/Odometry in CDR) or as a buffer read from a recording.
"""

from __future__ import annotations

import heapq
import json
import logging
import os
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from spiel_edge.errors import ConfigError, InputError
from spiel_edge.robot import record_check
from spiel_edge.robot.clock import MAX_BACKLOG_S, MAX_DISAGREEMENT_S, Disagreement, StampClock
from spiel_edge.robot.coast import CoastPolicy
from spiel_edge.robot.description import RobotSpec
from spiel_edge.robot.fusion import BoardReport, Fuser, stamp_latency
from spiel_edge.robot.odometry import OdometryBuffer
from spiel_edge.robot.record_check import Refused

log = logging.getLogger(__name__)

MAX_RECORD_BYTES = record_check.MAX_RECORD_BYTES
BAD_RECORDS_LIMIT = 20  # this many of its own bad records in a row: the board is reported dropped
RESET_AGREE = 4  # stamps off a board's clock, agreeing with each other: it restarted
NOT_THE_BOARDS = ("forged", "replayed")  # refused: not the board's own messages
NOT_HELD = (*NOT_THE_BOARDS, "flood")  # refused, but not held against the board


class RecordFuse:
    """Board records in (``handle``), fused records out to ``sink``. ``odometry``: a buffer
    of the robot's poses (a recording's) to track in odom; ``odom_messages``: odometry comes
    as messages (:meth:`handle_odometry`) into a live buffer. ``live``: stamp each fused
    record's latency (the write against the acquisitions' ``host_time``, one clock)."""

    def __init__(
        self,
        robot: RobotSpec,
        sink,
        *,
        track: bool = True,
        spec=None,
        odometry: OdometryBuffer | None = None,
        odom_messages: bool = False,
        live: bool = True,
    ):
        self.robot = robot
        self.sink = sink
        self.live = live
        self.odometry = odometry if odometry is not None else OdometryBuffer()
        use_odom = odometry is not None or odom_messages
        self.fuser = Fuser(
            {b.name: b.mount for b in robot.boards},
            period_s=robot.trigger.period_ms / 1000.0,
            spec=spec or robot.track_spec(),
            frame_id=robot.frame_id,
            field_of_view_deg={b.name: b.field_of_view_deg for b in robot.boards},
            coast=CoastPolicy.from_robot(robot),
            track=track,
            odometry=self.odometry if use_odom else None,
        )
        self.clocks = {b.name: StampClock() for b in robot.boards}
        self.synced: dict[str, bool] = {}  # per board: its records carry stamp_host
        self.bad = dict.fromkeys(self.clocks, 0)  # its own bad records in a row
        self.refused: dict[str, dict[str, int]] = {}  # per board: reason -> messages refused
        self._count_lock = threading.Lock()
        self.off_clock: dict[str, list[float]] = {}
        self.disagree = {name: Disagreement() for name in self.clocks}  # computers' clocks
        self.dropped: dict[str, str] = {}
        self.absent: set[str] = set()  # boards of the robot not in a replay
        self.records = 0
        self.latencies_ms: list[float] = []

    def handle(self, name: str, payload: bytes, arrived: float, refused: str | None = None) -> None:
        """One board record (its bytes) that reached this process at ``arrived`` (Unix s);
        ``refused``: the transport already refused it (``forged``, ``replayed``, ``too
        large``). A bad message costs that message only: it is counted and dropped
        (record_check.py), and only a board whose every message for BAD_RECORDS_LIMIT in a
        row was its own bad one is reported dropped, until a good record comes again."""
        try:
            if refused is not None:
                raise Refused(refused)
            report = self._report(name, payload, arrived)
            records = self.fuser.add(report)
        except Refused as exc:
            self._refuse(name, exc)
            return
        except Exception as exc:  # a bug: still, no peer's message ends the fusion
            log.error("board %s: a record raised %s (a bug in spiel-edge; dropped)", name, exc)
            self._refuse(name, Refused("internal error"))
            return
        self._accept(name)
        for record in records:
            self._write(record)

    def finish(self) -> None:
        """The stream ended: fuse every open cycle."""
        for record in self.fuser.flush():
            self._write(record)

    def _report(self, name: str, payload: bytes, arrived: float) -> BoardReport:
        fields = record_check.fields(record_check.parse(payload))
        stamp, remote = fields["stamp"], fields["remote"]
        late = arrived - remote  # delivery only delays: a time from the future is absurd,
        # and so is one older than any backlog a loaded reader runs (1.3-1.7 s were seen)
        absurd = late < -MAX_DISAGREEMENT_S or late > MAX_BACKLOG_S
        if absurd or self.disagree[name].observe(late, arrived):
            raise Refused(
                "clock",
                f"its computer's clock is {remote - arrived:+.2f} s off this one's "
                "(synchronise them: chrony or PTP)",
            )
        synced = fields["synced"]  # protocol 2: the board's time on its host's clock
        if synced:
            if abs(synced - remote) > MAX_DISAGREEMENT_S:
                raise Refused("stamp", "stamp_host is not the acquisition's time")
            stamp = synced  # its host's clock, mapped to this one's below
        if bool(synced) != self.synced.get(name, False):  # another time axis: learn it afresh
            self.synced[name] = bool(synced)
            self.clocks[name] = StampClock()
        self._check_stamp(name, stamp, arrived)
        clock = self.clocks[name]
        clock.observe(stamp, arrived)
        return BoardReport(
            name,
            clock.to_host(stamp),
            fields["targets"],
            acquisition=fields["acquisition"],
            device_time_us=fields["device_time_us"],
            crosstalk=fields["crosstalk"],
            error=fields["error"],
            acquired_unix=remote,  # the acquisition's end on its own computer
            received_unix=arrived if self.live else None,  # its record's arrival here
        )

    def _check_stamp(self, name: str, stamp: float, arrived: float) -> None:
        """A stamp far off the board's learned clock is one absurd message, refused, or the
        board restarted: RESET_AGREE such stamps in a row that agree with each other start
        its clock afresh."""
        clock = self.clocks[name]
        if not clock.ready or abs(clock.to_host(stamp) - arrived) <= MAX_DISAGREEMENT_S:
            self.off_clock[name] = []
            return
        offsets = self.off_clock.setdefault(name, [])
        offsets.append(arrived - stamp)
        if len(offsets) >= RESET_AGREE and max(offsets) - min(offsets) <= MAX_DISAGREEMENT_S:
            self.clocks[name] = StampClock()  # a restart: its new time axis
            self.off_clock[name] = []
            return
        del offsets[:-RESET_AGREE]
        raise Refused("stamp", "off the board's clock")

    def count_refused(self, name: str, reason: str, detail: str = "") -> int:
        """Count one refused message (thread-safe: Zenoh's threads count the forged and
        the flood); warn on the first of each reason and every 1000th. Its count so far."""
        with self._count_lock:
            counts = self.refused.setdefault(name, {})
            counts[reason] = n = counts.get(reason, 0) + 1
        if n == 1 or n % 1000 == 0:
            what = f"{reason}: {detail}" if detail else reason
            log.warning("board %s: message refused (%s; %d so far)", name, what, n)
        return n

    def _refuse(self, name: str, exc: Refused) -> None:
        self.count_refused(name, exc.reason, str(exc).partition(": ")[2])
        if exc.reason in NOT_HELD:
            return  # someone else's message, or too many: it says nothing about the board
        self.bad[name] = self.bad.get(name, 0) + 1
        if self.bad[name] >= BAD_RECORDS_LIMIT and name not in self.dropped:
            why = (
                f"{exc} (synchronise them: chrony or PTP)"
                if exc.reason == "clock"
                else f"its messages are not spiel-edge records ({exc})"
            )
            self._drop(name, why)

    def _accept(self, name: str) -> None:
        self.bad[name] = 0
        if name in self.dropped:
            del self.dropped[name]
            self.fuser.restore(name)
            log.warning("board %s is back: its records are fused again", name)

    def handle_odometry(self, payload: bytes, arrived: float) -> None:
        """An odometry message (JSON or a ROS 2 nav_msgs/msg/Odometry in CDR: the robot's
        planar pose in odom), see OdometryBuffer.add_message."""
        self.odometry.add_message(payload, arrived)

    def _drop(self, name: str, why: str) -> None:
        self.dropped[name] = why
        self.fuser.drop(name)
        log.warning("board %s dropped, the others go on: %s", name, why)

    def _write(self, record: dict) -> None:
        if self.live:
            stamp_latency(record, time.time(), self.latencies_ms)
        for name, why in self.dropped.items():
            record.setdefault("dropped", {})[name] = why
        self.sink.write(record)
        self.records += 1

    def summary(self) -> str:
        lat = np.array(self.latencies_ms)
        latency = (
            f"; latency after the last board's acquisition median {np.median(lat):.2f} ms, "
            f"p95 {np.percentile(lat, 95):.2f} ms"
            if lat.size
            else ""
        )
        boards = "; ".join(
            f"{n}: dropped ({self.dropped[n]})"
            if n in self.dropped
            else f"{n}: not replayed"
            if n in self.absent
            else f"{n}: {s['reports']} records, {s['targets']} targets"
            + (f", {s['no_pose']} without a pose" if s["no_pose"] else "")
            + self._refused_text(n)
            for n, s in self.fuser.stats.items()
        )
        return f"{self.records} fused records{latency}; {boards}"

    def _refused_text(self, name: str) -> str:
        with self._count_lock:
            counts = dict(self.refused.get(name) or {})
        if not counts:
            return ""
        parts = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
        return f", {sum(counts.values())} messages refused ({parts})"

    @property
    def forged(self) -> int:
        """Messages refused as not their board's (forged or replayed), over every board."""
        with self._count_lock:
            return sum(c.get(r, 0) for c in self.refused.values() for r in NOT_THE_BOARDS)


def read_replay(
    robot: RobotSpec, files: dict[str, str | Path]
) -> Iterator[tuple[float, str, bytes]]:
    """Boards' records from files (NDJSON, as ``run -o`` writes them, or the MCAP of ``run
    --record``, either profile: its /spiel/position records) as (host_time, board, line) in
    the order to fuse them: each file is in its own time order, so they are merged as they are
    read (memory does not grow with the drive's length). A name the robot does not have, or a
    file that cannot be opened: ConfigError or InputError at once, before anything is read.
    An unreadable line stays in its place (a bad record)."""
    known = {b.name for b in robot.boards}
    unknown = sorted(set(files) - known)
    if unknown:
        raise ConfigError(
            f"--replay: the robot has no board {unknown[0]!r} (boards: {', '.join(sorted(known))})"
        )
    for name, path in files.items():
        try:
            with open(path, "rb") as f:
                f.read(1)
        except OSError as exc:
            raise InputError(f"{path}: cannot read board {name}'s records: {exc.strerror}") from exc
    streams = [_timed(name, _record_lines(Path(path))) for name, path in files.items()]
    return heapq.merge(*streams, key=lambda item: (item[0], item[1]))


def replay(
    robot: RobotSpec,
    sink,
    streams: Iterable[tuple[float, str, bytes]],
    *,
    track: bool = True,
    spec=None,
    odometry: OdometryBuffer | None = None,
    boards: Iterable[str] | None = None,
) -> RecordFuse:
    """:func:`read_replay`'s records fused offline, each taken as arriving at its
    ``host_time`` (one computer's clock), optionally in odom with a recording's poses; the
    robot's boards not in ``boards`` (default: every board) are left out. Bad records count
    as live (a board with too many in a row is dropped)."""
    fuse = RecordFuse(robot, sink, track=track, spec=spec, odometry=odometry, live=False)
    present = set(boards) if boards is not None else {b.name for b in robot.boards}
    for b in robot.boards:
        if b.name not in present:
            fuse.fuser.drop(b.name)  # not replayed: no cycle waits for it
            fuse.absent.add(b.name)
    for t, name, line in streams:
        fuse.handle(name, line, t)
    fuse.finish()
    return fuse


def _timed(name: str, lines: Iterable[bytes]) -> Iterator[tuple[float, str, bytes]]:
    """(host_time, board, line); an unreadable line takes the time of the last good one, so it
    stays where it is in the file."""
    last = 0.0
    for line in lines:
        if line.strip():
            t = _host_time(line)
            last = t if t is not None else last
            yield last, name, line


def _record_lines(path: Path) -> Iterator[bytes]:
    """The JSON records of an NDJSON file, line by line, or of an MCAP recording's position
    topic (JSON, or std_msgs/String in CDR; a damaged file read as far as it goes)."""
    with open(path, "rb") as f:
        if not f.read(8).startswith(b"\x89MCAP"):
            f.seek(0)
            yield from f
            return
        from spiel_edge.messages.cdr import ENCAPSULATION, decode_string
        from spiel_edge.recordings.mcap_reader import POSITION_TOPIC
        from spiel_edge.recordings.mcap_scan import McapScanner

        for msg in McapScanner(f, os.fstat(f.fileno()).st_size).messages():
            if msg.topic != POSITION_TOPIC:
                continue
            data = msg.data
            if data[:4] == ENCAPSULATION:
                try:
                    data = decode_string(data).encode()
                except InputError:
                    data = b"not a record"  # counted as a bad record
            yield data


def _host_time(line: bytes) -> float | None:
    """A record's ``host_time`` for ordering (None: unreadable)."""
    try:
        t = float(json.loads(line)["host_time"])
    except (ValueError, KeyError, TypeError):
        return None
    return t if np.isfinite(t) else None
