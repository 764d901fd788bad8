"""``spiel-edge run --robot FILE``: every board of a robot served from one process.

One thread per board (robot/board_worker.py; the GIL keeps them on one core) owns the board's
link and session, its pipeline and its clock estimate, and keeps its stream in the board's
trigger slot, so a board that is unplugged, slow or gone stalls nobody else. The main thread
(:class:`RobotRunner`) starts every stream in its slot of one cycle, marks acquisitions
another board's pulse reached, fuses every board's targets in ``base_link``
(robot/fusion.py) and writes the fused records.

A board that never answers (its HELLO times out) is dropped with a warning and the rest go on;
a board whose clock disagrees with the host's by seconds is dropped the same way; when no
board is left the command fails with one line.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import sys
import threading
import time

import numpy as np

from spiel_edge.errors import SpielError
from spiel_edge.robot.board_worker import BoardWorker
from spiel_edge.robot.clock import unix_minus_perf_s
from spiel_edge.robot.coast import CoastPolicy
from spiel_edge.robot.description import RobotSpec
from spiel_edge.robot.fusion import BoardReport, Fuser, stamp_latency
from spiel_edge.robot.odometry import OdometryBuffer
from spiel_edge.robot.schedule import CrosstalkMarker, Schedule

log = logging.getLogger(__name__)

SWITCH_INTERVAL_S = 0.005  # the GIL switch interval while serving (Python default 0.005)


class RobotRunner:
    """Every board of ``robot`` in its thread; fused records to ``sink``."""

    def __init__(
        self,
        robot: RobotSpec,
        sink,
        *,
        association: str | None = None,
        max_targets: int | None = None,
        toa_correction: str | None = None,
        reconnect_timeout: float | None = None,
        track: bool = True,
        spec=None,
        odom_key: str | None = None,
    ):
        self.robot = robot
        self.sink = sink
        # the robot's pose in odom, on this process's clock (the boards' times are
        # perf_counter's), from a Zenoh key: JSON or nav_msgs/Odometry (robot/odometry.py)
        self.odometry = OdometryBuffer() if odom_key else None
        self._odom_feed = None  # its Zenoh subscription
        self.schedule = Schedule.from_robot(robot)
        self.stop = threading.Event()
        self.queue: queue.Queue = queue.Queue(maxsize=1024)
        self.t0 = 0.0  # slots count from here: set once every board is open
        # each board prepared as `run` prepares one (its ToA correction chosen there)
        self.workers = [
            BoardWorker(
                b,
                self.schedule,
                self.t0,
                self.queue,
                self.stop,
                association=association,
                max_targets=max_targets,
                toa_correction=toa_correction,
                reconnect_timeout=reconnect_timeout,
            )
            for b in robot.boards
        ]
        self.marker = CrosstalkMarker(self.schedule, [b.name for b in robot.boards])
        self.fuser = Fuser(
            {b.name: b.mount for b in robot.boards},
            period_s=self.schedule.period_s,
            frame_id=robot.frame_id,
            field_of_view_deg={b.name: b.field_of_view_deg for b in robot.boards},
            coast=CoastPolicy.from_robot(robot),
            track=track,
            spec=spec or robot.track_spec(),
            odometry=self.odometry,
            unix_offset=unix_minus_perf_s,  # records in Unix time, as `run`'s
        )
        if odom_key:  # its messages join the boards' reports in the queue (one reader)
            from spiel_edge.robot.odometry_sources import OdometrySubscription

            self._odom_feed = OdometrySubscription(
                odom_key,
                lambda payload, arrived: _put(self.queue, ("odom", None, (payload, arrived))),
            )
        self.records = 0
        self.latencies_ms: list[float] = []
        self.on_record = None  # each fused record, after the outputs have it (a library run)

    def run(self, stop: threading.Event | None = None, *, frames: int | None = None) -> int:
        """Until ``stop`` or ``frames`` fused records; returns the records written."""
        stop = stop or threading.Event()
        switch = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL_S)  # a board's thread waits less for another's
        for w in self.workers:
            w.start()
        alive = {w.board.name for w in self.workers}
        try:
            self._start_streams(stop)
            while not stop.is_set() and alive:
                try:
                    kind, name, payload = self.queue.get(timeout=0.1)
                except queue.Empty:
                    continue
                if kind == "drop":
                    alive.discard(name)
                    self.fuser.drop(name)
                    continue
                if kind == "odom":
                    self._odometry(*payload)
                    continue
                report: BoardReport = payload
                report.crosstalk = self.marker.observe(
                    name, report.host_time, uncertainty_s=report.time_uncertainty_s
                )
                for record in self.fuser.add(report):
                    self._write(record, report)
                if frames is not None and self.records >= frames:
                    break
            if not alive:
                from spiel_edge.errors import DeviceError

                raise DeviceError(
                    "no board is left: "
                    + "; ".join(f"{w.board.name}: {w.stats.dropped}" for w in self.workers)
                )
        finally:
            self.stop.set()
            for w in self.workers:
                w.join(timeout=3.0)
            sys.setswitchinterval(switch)
            self.close_odometry()
        return self.records

    def _odometry(self, payload: bytes, arrived: float) -> None:
        """A pose onto the boards' clock (Unix time onto perf_counter's axis)."""
        self.odometry.add_message(payload, arrived, time.perf_counter() - time.time())

    def close_odometry(self) -> None:
        """The odometry subscription closed (once; also when the run never started)."""
        feed, self._odom_feed = self._odom_feed, None
        if feed is not None:
            feed.close()

    def _start_streams(self, stop: threading.Event) -> None:
        """Every open board's stream started in its slot of one cycle, from this thread while
        the boards' threads wait (nothing else runs, so each start lands on time)."""
        for w in self.workers:
            while not w.ready.wait(0.1):
                if stop.is_set():
                    return
        t0 = time.perf_counter() + 0.02
        for w in self.workers:
            w.t0 = t0
        self.t0 = t0
        self.fuser.set_schedule(t0, {n: s.offset_s for n, s in self.schedule.slots.items()})
        order = sorted(self.workers, key=lambda w: self.schedule.slots[w.board.name].offset_s)
        for w in order:
            if w.stats.dropped or w.pipeline is None:
                continue
            if stop.is_set():
                return
            try:
                w.start_stream(self.schedule.fire_time(w.board.name, t0, 0))
            except SpielError as exc:
                w.stats.dropped = str(exc)  # its thread reports the drop
        for w in self.workers:
            w.go.set()

    def _write(self, record: dict, last: BoardReport) -> None:
        stamp_latency(record, time.time(), self.latencies_ms)  # after the last acquisition
        for name, diag in record["boards"].items():
            w = next(w for w in self.workers if w.board.name == name)
            diag["restarts"] = w.stats.restarts
        self.sink.write(record)
        self.records += 1
        if self.on_record is not None:
            self.on_record(record)

    def summary(self) -> str:
        parts = []
        for w in self.workers:
            s = w.stats
            state = f"dropped ({s.dropped})" if s.dropped else f"{s.acquisitions} acquisitions"
            marked = self.marker.marked.get(w.board.name, 0)
            no_pose = self.fuser.stats[w.board.name]["no_pose"]
            extra = f", {no_pose} without a pose" if no_pose else ""
            parts.append(f"{w.board.name}: {state}, {marked} marked, {s.restarts} restarts{extra}")
        lat = np.array(self.latencies_ms)
        latency = (
            f"; latency median {np.median(lat):.2f} ms, p95 {np.percentile(lat, 95):.2f} ms"
            if lat.size
            else ""
        )
        return f"{self.records} fused records{latency}; " + "; ".join(parts)


def _put(q: queue.Queue, item) -> None:
    with contextlib.suppress(queue.Full):
        q.put_nowait(item)
