"""``spiel-edge run --robot FILE``: every board of a robot served from one process.

One thread per board (the GIL keeps them on one core) owns the board's link and session, its
pipeline and its clock estimate, so a board that is unplugged, slow or gone stalls nobody
else: its session waits for it to come back (docs/integrator.md) while the others stream.
Each thread starts its board's stream in the board's trigger slot (robot/schedule.py) and
keeps it there: it maps the board's stamps to the host's clock (robot/clock.py), and when a
pulse strays more than half the sync margin from the slot, it restarts the stream at the
slot's next start. The main thread marks acquisitions another board's pulse reached, fuses
every board's targets in ``base_link`` (robot/fusion.py) and writes the fused records.

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
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from spiel_edge.device import DeviceSession
from spiel_edge.errors import DeviceError, SpielError
from spiel_edge.robot.clock import MAX_DISAGREEMENT_S, StampClock, synced_pulse, wait_until
from spiel_edge.robot.coast import CoastPolicy
from spiel_edge.robot.description import BoardSpec, RobotSpec
from spiel_edge.robot.fusion import BoardReport, Fuser, reports_targets
from spiel_edge.robot.odometry import OdometryBuffer
from spiel_edge.robot.schedule import CrosstalkMarker, Schedule

log = logging.getLogger(__name__)

SWITCH_INTERVAL_S = 0.005  # the GIL switch interval while serving (Python default 0.005)
PHASE_CHECK_EVERY = 8  # acquisitions between slot checks
PHASE_SETTLE = 8  # acquisitions after a (re)start that fix the link's constant latency
DISAGREE_LIMIT = 3  # acquisitions in a row seconds off the clock estimate: the board is dropped


@dataclass
class WorkerStats:
    acquisitions: int = 0
    errors: int = 0
    restarts: int = 0
    dropped: str | None = None
    counts: dict = field(default_factory=dict)


class BoardWorker(threading.Thread):
    """One board: session, pipeline, clock, slot keeping. Reports go to ``out``."""

    def __init__(
        self,
        board: BoardSpec,
        schedule: Schedule,
        t0: float,
        out: queue.Queue,
        stop: threading.Event,
        *,
        association: str | None = None,
        max_targets: int | None = None,
        toa_correction: str | None = None,
        reconnect_timeout: float | None = None,
        open_timeout_s: float = 5.0,
    ):
        super().__init__(name=f"board-{board.name}", daemon=True)
        self.board = board
        self.schedule = schedule
        self.t0 = t0
        self.out = out
        self.stop = stop
        self.association = association
        self.max_targets = max_targets
        self.toa_correction = toa_correction
        self.open_timeout_s = open_timeout_s
        self.session = DeviceSession(board.port, reconnect_timeout_s=reconnect_timeout)
        self.clock = StampClock()
        self.stats = WorkerStats()
        self.pipeline = None
        self.ready = threading.Event()  # set once the board is open (or dropped)
        self.go = threading.Event()  # set by the runner once every stream started in its slot
        self._bias: list[float] = []
        self._bias_s = 0.0
        self._timed = None  # the stream this thread started in the slot (StreamStartResponse)
        self.synced = False  # its pulses come from TIME_SYNC (protocol 2), not the estimate
        self._recent: deque[float] = deque(maxlen=PHASE_CHECK_EVERY)
        self._disagree = 0

    # --- thread ------------------------------------------------------------------------

    def run(self) -> None:
        try:
            self._open()
            self.ready.set()  # the runner starts the stream in the slot, then says go
            while not self.go.wait(0.1):
                if self.stop.is_set():
                    return
            if self.session.stream is None:
                raise DeviceError(self.stats.dropped or "its stream did not start")
            self._loop()
        except SpielError as exc:
            self._drop(str(exc))
        except Exception as exc:  # a bug in one board's thread must not take the others
            log.debug("board %s", self.board.name, exc_info=True)
            self._drop(f"unexpected error: {type(exc).__name__}: {exc}")
        finally:
            self.ready.set()
            with contextlib.suppress(DeviceError):
                self.session.close()

    def _drop(self, why: str) -> None:
        self.stats.dropped = why
        log.warning("board %s dropped, the others go on: %s", self.board.name, why)
        self.out.put(("drop", self.board.name, why))

    def _open(self) -> None:
        from spiel_edge.runtime.loop import open_pipeline

        b = self.board
        pipeline, _ = open_pipeline(
            self.session,
            b.profile,
            b.calibration,
            self.association,
            use_board=b.calibration is None,
            toa_correction=self.toa_correction,
        )
        if self.max_targets:
            pipeline.set_max_targets(self.max_targets)
        self.pipeline = pipeline

    def _start_in_slot(self) -> None:
        """(Re)start the stream at the slot's next start (from the board's own thread)."""
        at = self.schedule.next_fire(self.board.name, self.t0, time.perf_counter() + 0.01)
        if wait_until(at, self.stop):
            self.start_stream_now()

    def start_stream_now(self) -> None:
        sched = self.schedule
        n_samples = self.pipeline.profile.acquisition.n_samples
        period = sched.period_s / (1.0 + self.clock.drift) if self.clock.ready else sched.period_s
        self._timed = self.session.start_stream(rate_hz=1.0 / period, n_samples=n_samples)
        self._bias = []
        self._recent.clear()

    def _loop(self) -> None:
        window = self.schedule.window_s
        for acq in self.session.acquisitions(self.stop):
            arrival = acq.received_ns / 1e9
            stamp = acq.timestamp_us / 1e6
            late = self.clock.observe(stamp, arrival)
            if self.clock.ready and abs(late) > MAX_DISAGREEMENT_S:
                self._disagree += 1
                if self._disagree >= DISAGREE_LIMIT:
                    raise DeviceError(
                        f"its clock disagrees with the host's by {late:+.1f} s "
                        f"(stamps not in microseconds, or a clock that jumps)"
                    )
            else:
                self._disagree = 0
            pulse = synced_pulse(acq)  # protocol 2: TIME_SYNC's mapping of the board's clock
            if (pulse is not None) != self.synced:  # another time axis: learn the bias afresh
                self.synced = pulse is not None
                self._bias = []
                self._recent.clear()
            if pulse is None:  # protocol 1: the one-way estimate from the stamps' arrivals
                pulse = self.clock.to_host(stamp) - window
            timed = self._timed
            if self.session.stream is not timed or timed is None:
                # the session restarted the stream itself (the board came back): not in a
                # slot; reported as measured, and put back in its slot at once
                off_slot, t = self.clock.ready, pulse
            elif (acq.index - timed.first_acquisition) & 0xFFFFFFFF >= 1 << 31:
                off_slot, t = False, pulse  # left over from before the last start
            else:
                off_slot = self._off_slot(pulse)
                t = self._on_schedule(pulse - self._bias_s)
            report = self._report(acq, t, arrival)
            self.stats.acquisitions += 1
            self.out.put(("report", self.board.name, report))
            if off_slot:
                self.stats.restarts += 1
                log.info("board %s left its slot; restarting it in the slot", self.board.name)
                self._start_in_slot()

    def _report(self, acq, pulse: float, arrival: float) -> BoardReport:
        error = None
        result = None
        try:
            background = None if acq.background is None else acq.background.astype(np.float64)
            result = self.pipeline.process(acq.samples.astype(np.float64), background)
        except SpielError as exc:
            self.stats.errors += 1
            error = str(exc)
        truth = acq.truth_targets_mm
        if truth is not None:
            truth = self.board.mount.to_base(np.asarray(truth, float))
        return BoardReport(
            self.board.name,
            pulse,
            reports_targets(result),
            acquisition=acq.index,
            device_time_us=acq.timestamp_us,
            error=error,
            truth_mm=truth,
            acquired_unix=acq.host_time,
        )

    def _on_schedule(self, t: float) -> float:
        """A board whose pulses sit within the sync margin of its slot (the median of the last
        few: a periodic stream does not jump for one pulse, an estimate's outlier does) is
        taken to fire at the slot's time; otherwise the pulse keeps its measured time."""
        sched, offset = self.schedule, self.schedule.slots[self.board.name].offset_s
        k = round((t - self.t0 - offset) / sched.period_s)
        slot = self.t0 + k * sched.period_s + offset
        err = float(np.median(self._recent)) - self._bias_s if self._recent else t - slot
        return slot if abs(err) <= sched.margin_s else t

    def _off_slot(self, pulse: float) -> bool:
        """Whether the board's pulses left its slot. The first ``PHASE_SETTLE`` pulses after a
        start the host timed fix the board's bias (the link's smallest latency, which one-way
        stamps cannot see, plus how late the start landed): pulses are reported less it, and
        only a change of phase (the median of the last few) beyond the sync margin counts."""
        if not self.clock.ready:
            return False
        err = self.schedule.phase_error(self.board.name, self.t0, pulse)
        if len(self._bias) < PHASE_SETTLE:
            self._bias.append(err)
            self._bias_s = float(np.median(self._bias))
            return False
        self._recent.append(err)
        if self.stats.acquisitions % PHASE_CHECK_EVERY:
            return False
        return abs(float(np.median(self._recent)) - self._bias_s) > self.schedule.margin_s


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
        self._odom_session = None
        self.schedule = Schedule.from_robot(robot)
        self.stop = threading.Event()
        self.queue: queue.Queue = queue.Queue(maxsize=1024)
        self.t0 = 0.0  # slots count from here: set once every board is open
        self.workers = [
            BoardWorker(
                b,
                self.schedule,
                self.t0,
                self.queue,
                self.stop,
                association=association,
                max_targets=max_targets,
                toa_correction=_toa(b.port, toa_correction),
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
        )
        if odom_key:
            self._subscribe_odometry(odom_key)
        self.records = 0
        self.latencies_ms: list[float] = []

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
                report.crosstalk = self.marker.observe(name, report.host_time)
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
            self._close_odometry()
        return self.records

    def _subscribe_odometry(self, key: str) -> None:
        """A Zenoh subscriber whose messages join the boards' reports in the queue (the
        buffer is read and written by the main thread only)."""
        from spiel_edge.errors import ConfigError
        from spiel_edge.outputs.zenoh import _import_zenoh
        from spiel_edge.robot.zenoh_fuse import zenoh_config

        zenoh = _import_zenoh()

        def on_sample(sample) -> None:
            with contextlib.suppress(queue.Full):
                self.queue.put_nowait(("odom", None, (sample.payload.to_bytes(), time.time())))

        try:
            self._odom_session = zenoh.open(zenoh_config())
            self._odom_session.declare_subscriber(key, on_sample)
        except Exception as exc:  # zenoh.ZError
            self._close_odometry()
            raise ConfigError(f"--odom {key}: cannot subscribe on Zenoh: {exc}") from exc

    def _odometry(self, payload: bytes, arrived: float) -> None:
        """A pose onto the boards' clock (Unix time onto perf_counter's axis)."""
        self.odometry.add_message(payload, arrived, time.perf_counter() - time.time())

    def _close_odometry(self) -> None:
        if self._odom_session is not None:
            with contextlib.suppress(Exception):  # zenoh.ZError on a closing session
                self._odom_session.close()
            self._odom_session = None

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
            if not wait_until(self.schedule.fire_time(w.board.name, t0, 0), stop):
                return
            try:
                w.start_stream_now()
            except SpielError as exc:
                w.stats.dropped = str(exc)  # its thread reports the drop
        for w in self.workers:
            w.go.set()

    def _write(self, record: dict, last: BoardReport) -> None:
        acquired = [b["acquired"] for b in record["boards"].values() if "acquired" in b]
        if acquired:  # after the last board's acquisition reached this host
            latency = (time.time() - max(acquired)) * 1e3
            record["latency_ms"] = round(latency, 3)
            self.latencies_ms.append(latency)
        for name, diag in record["boards"].items():
            w = next(w for w in self.workers if w.board.name == name)
            diag["restarts"] = w.stats.restarts
        self.sink.write(record)
        self.records += 1

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


def _toa(port: str, requested: str | None) -> str | None:
    from spiel_edge.runtime.loop import live_toa_correction

    return live_toa_correction(port, requested)
