"""Board records fused in the robot's frame: the part of ``spiel-edge fuse`` that does not
depend on where the records come from (Zenoh live, robot/zenoh_fuse.py, or the files a board's
``run -o`` wrote, :func:`read_replay` and :func:`replay`).

A record is ``run``'s JSON (``targets``, ``device_time_us``, ``host_time``, ``stamp_host``
with protocol 2). Time: each board's stamps are mapped to this computer's clock from the
records' arrival (robot/clock.py's lower envelope, which absorbs the network's delay). A
board whose computer's clock (its records' ``host_time``) is more than a second off this
one's is dropped with a warning (synchronise them: chrony or PTP), as is a board whose
records are not records. Per-board diagnostics ride in every fused record (``boards``).
Odometry (``odom`` tracking) comes as messages (robot/odometry.py: JSON or a ROS 2
nav_msgs/msg/Odometry in CDR) or as a buffer read from a recording.
"""

from __future__ import annotations

import heapq
import json
import logging
import math
import os
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from spiel_edge.errors import ConfigError, InputError
from spiel_edge.robot.clock import Disagreement, StampClock
from spiel_edge.robot.coast import CoastPolicy
from spiel_edge.robot.description import RobotSpec
from spiel_edge.robot.fusion import BoardReport, Fuser, record_targets, stamp_latency
from spiel_edge.robot.odometry import OdometryBuffer

log = logging.getLogger(__name__)

MAX_RECORD_BYTES = 1 << 20  # a board record is a few kB; anything larger is refused
BAD_RECORDS_LIMIT = 20  # this many unreadable records in a row: the board is dropped


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
        self.bad = dict.fromkeys(self.clocks, 0)
        self.disagree = {name: Disagreement() for name in self.clocks}  # computers' clocks
        self.dropped: dict[str, str] = {}
        self.absent: set[str] = set()  # boards of the robot not in a replay
        self.records = 0
        self.latencies_ms: list[float] = []

    def handle(self, name: str, payload: bytes, arrived: float) -> None:
        """One board record (its bytes) that reached this process at ``arrived`` (Unix s)."""
        if name in self.dropped:
            return
        report = self._report(name, payload, arrived)
        if report is not None:
            for record in self.fuser.add(report):
                self._write(record)

    def finish(self) -> None:
        """The stream ended: fuse every open cycle."""
        for record in self.fuser.flush():
            self._write(record)

    def _report(self, name: str, payload: bytes, arrived: float) -> BoardReport | None:
        try:
            if len(payload) > MAX_RECORD_BYTES:
                raise ValueError(f"{len(payload)} bytes")
            fields = _record_fields(json.loads(payload))
        except (ValueError, KeyError, TypeError) as exc:
            self.bad[name] += 1
            if self.bad[name] >= BAD_RECORDS_LIMIT:
                self._drop(name, f"its messages are not spiel-edge records ({exc})")
            return None
        self.bad[name] = 0
        stamp, remote = fields["stamp"], fields["remote"]
        if self.disagree[name].observe(arrived - remote, arrived):
            self._drop(
                name,
                f"its computer's clock is {remote - arrived:+.2f} s off this one's "
                "(synchronise them: chrony or PTP)",
            )
            return None
        synced = fields["synced"]  # protocol 2: the board's time on its host's clock
        if synced:
            stamp = synced  # its host's clock, mapped to this one's below
        if bool(synced) != self.synced.get(name, False):  # another time axis: learn it afresh
            self.synced[name] = bool(synced)
            self.clocks[name] = StampClock()
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
            for n, s in self.fuser.stats.items()
        )
        return f"{self.records} fused records{latency}; {boards}"


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
        from spiel_edge.recordings.cdr import ENCAPSULATION, decode_string
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


def _record_fields(record) -> dict:
    """What the fuser takes from a board's record (``run``'s JSON); ValueError, KeyError or
    TypeError when it is not one (a wrong type anywhere is the whole record's fault)."""
    device_us = record["device_time_us"]
    remote = float(record["host_time"])
    if isinstance(device_us, bool) or not isinstance(device_us, (int, float)):
        raise TypeError("device_time_us is not a number")
    if not (math.isfinite(device_us) and math.isfinite(remote)):
        raise ValueError("non-finite time")
    acquisition = record.get("acquisition", -1)
    if isinstance(acquisition, bool) or not isinstance(acquisition, int):
        raise TypeError("acquisition is not an integer")
    targets = record.get("targets") or []
    crosstalk = record.get("crosstalk") or []
    if not isinstance(targets, list):
        raise TypeError("targets is not a list")
    if not (isinstance(crosstalk, list) and all(isinstance(b, str) for b in crosstalk)):
        raise TypeError("crosstalk is not a list of board names")
    synced = record.get("stamp_host")
    synced = (
        float(synced)
        if isinstance(synced, (int, float))
        and not isinstance(synced, bool)
        and math.isfinite(synced)
        else 0.0
    )
    return {
        "stamp": float(device_us) / 1e6,
        "remote": remote,
        "synced": synced,
        "acquisition": acquisition,
        "device_time_us": int(device_us),
        "targets": record_targets(record),
        "crosstalk": crosstalk,
        "error": str(record.get("reason")) if record.get("error") else None,
    }
