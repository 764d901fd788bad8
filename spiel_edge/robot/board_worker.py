"""One board of ``run --robot`` in its own thread (robot/serve.py runs them): its link and
session, its pipeline and its clock estimate, so a board that is unplugged, slow or gone
stalls nobody else: its session waits for it to come back (docs/integrator.md) while the
others stream. The board is prepared and opened as `run` opens one (runtime/live.py's
LiveRun: the profile resolved, the ToA correction chosen and the pipeline built once) and
its acquisitions come through `run`'s live loop (LiveRunner), whose step here reports the
targets to the fusion instead of writing a record. The thread keeps its board's stream in
the board's trigger slot (robot/schedule.py): it maps the board's stamps to the host's clock
(robot/clock.py), and when its pulses stray more than the sync margin from the slot, it
restarts the stream at the slot's next start. Its reports go to the runner's queue."""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass, field

from spiel_edge.errors import DeviceError, SpielError
from spiel_edge.robot.clock import (
    Disagreement,
    StampClock,
    synced_pulse,
    unix_minus_perf_s,
    wait_until,
)
from spiel_edge.robot.description import BoardSpec
from spiel_edge.robot.fusion import BoardReport, reports_targets
from spiel_edge.robot.schedule import Schedule
from spiel_edge.robot.slot_keeper import SlotPhase, StartAtTrust
from spiel_edge.robot.slot_session import start_in_time
from spiel_edge.runtime.live import LiveConfig, LiveRun

log = logging.getLogger(__name__)


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
        self.phase = SlotPhase(schedule, board.name, t0)  # its pulses against its slot
        self.out = out
        self.stop = stop
        self.open_timeout_s = open_timeout_s
        # prepared as `run` prepares a board: files, profile, ToA correction, pipeline (the
        # kernels are ready: run --robot compiled every board's before this)
        self.live = LiveRun(
            LiveConfig(
                port=board.port,
                profile=board.profile,
                calibration=board.calibration,
                use_board=board.calibration is None,
                association=association,
                max_targets=max_targets,
                toa_correction=toa_correction,
                reconnect_timeout=reconnect_timeout,
                track=False,  # the fusion tracks
                output=None,
                tiered=False,
            )
        )
        self.live.prepare()
        self.session = self.live.session
        self.clock = StampClock()
        self.stats = WorkerStats()
        self.ready = threading.Event()  # set once the board is open (or dropped)
        self.go = threading.Event()  # set by the runner once every stream started in its slot
        self._host_timed = False  # the host sent its last start (no START_AT)
        self._timed = None  # the stream this thread started in the slot (StreamStartResponse)
        self.synced = False  # its pulses come from TIME_SYNC (protocol 2), not the estimate
        self.on_its_clock = False  # its last start was named in its clock (START_AT)
        self.trust = StartAtTrust(schedule.margin_s)  # does it keep the time it is named?
        self._named: tuple[float, float] | None = None  # (when, period) of such a start
        self._disagree = Disagreement()  # seconds off the clock estimate: the board is dropped

    @property
    def pipeline(self):
        """The board's pipeline (None until it is open)."""
        return self.live.pipeline

    @property
    def t0(self) -> float:
        """Slots count from here (host time; the runner sets it once every board is open)."""
        return self.phase.t0

    @t0.setter
    def t0(self, value: float) -> None:
        self.phase.t0 = value

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
        self.live.open()
        runner = self.live.runner
        runner.step = self._step  # `run`'s loop; each acquisition reported here
        runner.background_hint = (
            f"board {self.board.name} sends none (`run --robot` takes no --background)"
        )

    def _start_in_slot(self) -> None:
        """(Re)start the stream at the slot's next start (from the board's own thread)."""
        at = self.schedule.next_fire(self.board.name, self.t0, time.perf_counter() + 0.01)
        self.start_stream(at)

    def start_stream(self, at: float) -> None:
        """Start the stream so that it fires at ``at`` (perf_counter's axis): named in the
        board's clock where it can be (START_AT, TIME_SYNC synced: no request latency, no
        waiting), else sent at that moment."""
        sched = self.schedule
        n_samples = self.pipeline.profile.acquisition.n_samples
        period = sched.period_s / (1.0 + self.clock.drift) if self.clock.ready else sched.period_s
        unix_at = at + unix_minus_perf_s()

        def by_host() -> bool:  # sent lead_s early: how late the earlier such starts landed
            lead = self.phase.lead_s
            fire = self.schedule.next_fire(
                self.board.name, self.t0, max(at, time.perf_counter() + lead)
            )
            return wait_until(fire - lead, self.stop)

        timed, named = start_in_time(
            self.session, self.trust, unix_at, 1.0 / period, by_host, n_samples=n_samples
        )
        self.on_its_clock = named
        self._named = (at, period) if named else None
        host_timed = not named
        if timed is None:  # stopping
            return
        self._timed = timed
        self._host_timed = host_timed
        self.phase.started(self.synced, host_timed)

    def _loop(self) -> None:
        self.live.run(self.stop)  # `run`'s live loop, with _step for each acquisition

    def _step(self, acq) -> None:
        """One acquisition: its pulse on the host's clock, its targets reported, and the
        stream put back in its slot when it left it."""
        arrival = acq.received_ns / 1e9
        stamp = acq.timestamp_us / 1e6
        late = self.clock.observe(stamp, arrival)
        if self.clock.ready and self._disagree.observe(late, arrival):
            raise DeviceError(
                f"its clock disagrees with the host's by {late:+.1f} s "
                f"(stamps not in microseconds, or a clock that jumps)"
            )
        pulse = self._measured_pulse(acq)  # protocol 2: TIME_SYNC's, when it is tight
        if (pulse is not None) != self.synced:  # another time axis: learn the bias afresh
            self.synced = pulse is not None
            self.phase.started(self.synced, self._host_timed)
        if pulse is None:  # protocol 1: the one-way estimate from the stamps' arrivals
            pulse = self.clock.to_host(stamp) - self.schedule.window_s
        timed = self._timed
        if self.session.stream is not timed or timed is None:
            # the session restarted the stream itself (the board came back): not in a slot;
            # reported as measured, and put back in its slot at once
            off_slot, t = self.clock.ready, pulse
        elif (acq.index - timed.first_acquisition) & 0xFFFFFFFF >= 1 << 31:
            off_slot, t = False, pulse  # left over from before the last start
        else:
            missed = (
                self._named is not None
                and self.synced
                and self._missed_named_start(acq.index - timed.first_acquisition, pulse)
            )
            t, off_slot = self.phase.observe(pulse)
            off_slot = off_slot or missed
        report = self._report(acq, t, arrival)
        self.stats.acquisitions += 1
        self.out.put(("report", self.board.name, report))
        if off_slot:
            self.stats.restarts += 1
            log.info("board %s left its slot; restarting it in the slot", self.board.name)
            self._start_in_slot()

    def _missed_named_start(self, k: int, pulse: float) -> bool:
        """The first pulse (the ``k``-th of the stream) after a start named in the board's
        clock: True when it missed the slot (the stream is restarted; a board that misses
        twice in a row is started by the host from then on)."""
        (at, period), self._named = self._named, None
        if self.trust.landed(at + (k & 0xFFFFFFFF) * period, pulse):
            return False
        if not self.trust.usable:
            log.warning(
                "board %s does not start at the time of its clock it is given; starting it "
                "by the host from now on",
                self.board.name,
            )
        return True

    def _report(self, acq, pulse: float, arrival: float) -> BoardReport:
        result, error = self.live.runner.process(acq)  # as `run` processes it
        self.stats.errors += error is not None
        truth = acq.truth_targets_mm
        if truth is not None:
            truth = self.board.mount.to_base(truth.astype(float))
        return BoardReport(
            self.board.name,
            pulse,
            reports_targets(result),
            acquisition=acq.index,
            device_time_us=acq.timestamp_us,
            error=error,
            truth_mm=truth,
            acquired_unix=acq.host_time,
            time_uncertainty_s=self._stamp_uncertainty(acq),
        )

    def _measured_pulse(self, acq) -> float | None:
        """TIME_SYNC's pulse time (protocol 2), taken as measured once its uncertainty is a
        quarter of the sync margin or less and until it passes half the margin (early
        exchanges bound it only to milliseconds); None: the one-way estimate's rules."""
        pulse = synced_pulse(acq)
        us = getattr(acq, "stamp_uncertainty_us", None)
        if pulse is None or us is None or not math.isfinite(us):
            return None
        limit = self.schedule.margin_s * (0.5 if self.synced else 0.25)
        return pulse if us * 1e-6 <= limit else None

    def _stamp_uncertainty(self, acq) -> float | None:
        """Seconds: how far the reported pulse may be from the true one, when TIME_SYNC
        measured it (the reported time is then the measured one: SlotPhase)."""
        us = getattr(acq, "stamp_uncertainty_us", None)
        return us * 1e-6 if self.synced and us is not None else None
