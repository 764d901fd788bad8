"""Run a board: the one place a live run is assembled (issue 42), for `spiel-edge run` and
for a library user.

A :class:`LiveConfig` says what to run (the port, the profile and calibration, the outputs,
the limits, tracking); :class:`LiveRun` does it in four steps, each once: ``prepare`` (every
file checked, the profile resolved, the ToA correction chosen, the pipeline built and sized,
the kernels' tier started on it: before the board is touched), ``open`` (the board; a second
pipeline only when the board's stored config changes the profile; the outputs), ``start``
(the stream, in its trigger slot with ``slot``), ``run`` and ``close``. A board of
``run --robot`` is opened the same way (robot/board_worker.py), with its own loop step.
:func:`run` is the whole of it::

    from spiel_edge.runtime.live import LiveConfig, run

    records = []
    stats = run(LiveConfig(port="sim://", frames=50, output=None), on_record=records.append)

The CLI (cli/run.py) maps its options onto a LiveConfig and adds what is a terminal's: the
signals, the status line, the lines on stderr and the exit status (docs/live-api.md).
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from spiel_edge.device import DeviceSession
from spiel_edge.errors import ConfigError, DeviceError
from spiel_edge.outputs import Sink, check_outputs, open_outputs
from spiel_edge.outputs.fanout import check_output_key
from spiel_edge.outputs.ros2_options import ros2_output_options
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import apply_calibration, load_profile
from spiel_edge.protocol import SampleFormat
from spiel_edge.runtime.loop import (
    LiveRunner,
    LiveStats,
    check_stream_shape,
    live_toa_correction,
    load_background,
    open_pipeline,
    warm_up,
)
from spiel_edge.runtime.realtime import apply_realtime
from spiel_edge.runtime.recorded import chosen_toa_correction
from spiel_edge.runtime.track_records import ResultTracker
from spiel_edge.safety.guard import FilePlan

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LiveConfig:
    """What one board's live run is (the options of `spiel-edge run`, docs/cli.md)."""

    port: str | None = None  # a port URL (docs/integrator.md); None: the one attached board
    frames: int | None = None  # stop after this many records (None: until stopped)
    profile: str = "spiel-icra23"  # built-in name or .toml path
    calibration: str | None = None
    use_board: bool = True  # the board's stored geometry over ``profile``
    association: str | None = None
    max_targets: int | None = None
    toa_correction: str | None = None  # None: live_toa_correction chooses
    rate: float = 50.0  # acquisitions per second asked of the board
    background: str | None = None  # a target-free capture file (else the board's, if any)
    reconnect_timeout: float | None = None
    track: bool = True
    samples: str = "envelope"  # or "iq"
    slot: str | None = None  # ROBOT:BOARD: fire in this board's trigger slot
    realtime: int | None = None
    # outputs: NDJSON file or "-" (None: none), MCAP recording, UDP, Foxglove, Zenoh
    output: str | None = "-"
    record: str | None = None
    udp: tuple[str, ...] = ()
    foxglove: str | None = None
    zenoh: str | None = None
    force: bool = False  # outputs may replace files
    # False: the caller has every kernel ready, nothing is tiered (run --robot compiles every
    # board's before any board opens: robot/live.py)
    tiered: bool = True
    # the outputs' ROS 2 and Zenoh options by their `run` names (record_profile, frame_id,
    # zenoh_encoding, ...: outputs/ros2_options.py); a key left out is the option's default
    ros2: Mapping[str, Any] = field(default_factory=dict)


class LiveRun:
    """One board's run: ``prepare()``, ``open()``, ``start(stop)``, ``run(stop)``, ``close()``.

    ``notifier``: pinged per record and told of a kernel compile's progress (systemd's,
    service/systemd.py; readiness is the caller's to say, after ``start``); ``in_slot``: with
    ``config.slot``, starts the stream in the board's trigger slot, ``in_slot(session, stop,
    stream options)`` -> an object with ``on_acquisition(acq)`` and ``summary()``
    (robot/slot_session.py's ``slot_starter``: the robot layer sits above this one)."""

    def __init__(self, config: LiveConfig, *, notifier=None, in_slot=None):
        if config.slot and in_slot is None:
            raise ConfigError(
                f"slot {config.slot!r}: give in_slot=robot.slot_session.slot_starter(slot)"
            )
        self.config = config
        self.notifier = notifier
        self.in_slot = in_slot if config.slot else None
        self.port = config.port
        self.profile = None  # the resolved profile (calibration applied)
        self.toa_correction = config.toa_correction
        self.tiers = None
        self.session: DeviceSession | None = None
        self.pipeline = None
        self.sink = None
        self.runner: LiveRunner | None = None
        self.slotted = None
        self._background = None
        self._prepared = None  # the pipeline built for ``profile`` before the board opens
        self._record = config.record
        self._base = None
        self._output_options: dict = {}

    def prepare(self) -> None:
        """Before the board: every input and output file checked, the profile resolved, the
        background read, the ToA correction chosen and the kernels' tier started (kernels
        missing from every cache: the interpreted ones run while a background process
        compiles them, said at once with progress)."""
        from spiel_edge.runtime.tiered import start_tiered

        c = self.config
        plan = FilePlan(c.force)  # every file checked before the board is touched
        for path, option in ((c.background, "--background"), (c.calibration, "--calibration")):
            if path:
                plan.input_file(path, option)
        plan.input_if_file(c.profile, "--profile")
        if c.slot:
            plan.input_if_file(c.slot.rpartition(":")[0], "--slot")
        self._record = check_outputs(plan, c.output, c.record)
        # a bad profile, calibration or frame option: before the board
        self._base = load_profile(c.profile)
        calibrated = apply_calibration(self._base, c.calibration) if c.calibration else None
        self.profile = calibrated or self._base
        self._output_options = ros2_output_options(c.ros2, self.profile)
        if c.zenoh is not None:
            check_output_key(c.zenoh, self._output_options["zenoh_encoding"])
        self._background = load_background(c.background) if c.background else None
        if self.port is None:  # USB scanning only when needed
            from spiel_edge.link.discover import default_port

            self.port = default_port()  # DeviceError naming the choices
        self.toa_correction = live_toa_correction(self.port, c.toa_correction)
        self._prepared = build_pipeline(self.profile, c.association, self.toa_correction)
        if c.max_targets:
            self._prepared.set_max_targets(c.max_targets)
        if c.tiered:  # the kernels exercised on this pipeline: it is the run's (built once)
            self.tiers = start_tiered(
                self.profile,
                c.association,
                c.max_targets,
                c.track,
                self.toa_correction,
                notifier=self.notifier,
                pipeline=self._prepared,
            )
        else:
            warm_up(self._prepared)
        apply_realtime(c.realtime)  # compiled: the link's and the outputs' threads inherit it
        self.session = DeviceSession(self.port, reconnect_timeout_s=c.reconnect_timeout)

    def open(self) -> None:
        """The board opened, its pipeline built and sized (once), the outputs opened and the
        live loop made (``runner``; the stream not started yet)."""
        c, session = self.config, self.session
        self.pipeline, source = open_pipeline(
            session,
            c.profile,
            c.calibration,
            c.association,
            use_board=c.use_board,
            toa_correction=self.toa_correction,
            max_targets=c.max_targets,
            chosen=True,
            resolved=(self._base, self.profile),
            prepared=self._prepared,
        )
        profile = self.pipeline.profile
        self.sink = self._open_sink(profile, source)
        tracker = ResultTracker(profile.track, profile.scene) if c.track else None
        runner = LiveRunner(
            session, self.pipeline, self.sink, background=self._background, tracker=tracker
        )
        runner.tiers = self.tiers
        if self.notifier is not None:
            runner.on_record = self.notifier.ping  # the service watchdog
        self.runner = runner

    def start(self, stop: threading.Event) -> None:
        """The stream started: at ``config.rate``, or in the board's trigger slot (``slotted``:
        its keeper); ConfigError when the board's stream does not fit the profile."""
        c, session, profile = self.config, self.session, self.pipeline.profile
        stream = dict(
            n_samples=profile.acquisition.n_samples,
            sample_format=SampleFormat.I16_IQ if c.samples == "iq" else SampleFormat.U16_ENVELOPE,
        )
        if self.in_slot is None:
            session.start_stream(rate_hz=c.rate, **stream)
        else:
            self.slotted = self.in_slot(session, stop, stream)
            self.runner.on_acquisition = self.slotted.on_acquisition
        check_stream_shape(session, self.pipeline)  # ConfigError when it does not fit

    def _open_sink(self, profile, source: str):
        c = self.config
        if c.output is None and not (c.record or c.udp or c.foxglove or c.zenoh):
            return Sink()  # a library run with no outputs: records go to on_record only
        return open_outputs(
            c.output,
            self._record,
            c.udp,
            c.foxglove,
            c.zenoh,
            receivers_mm=profile.geometry.channels_mm,
            metadata={
                "port": self.port,
                "profile": profile.name,
                "geometry": source,
                **chosen_toa_correction(self.toa_correction),
            },
            force=c.force,
            **self._output_options,
        )

    def run(self, stop: threading.Event, status=None) -> LiveStats:
        """Records until ``stop`` is set or ``frames`` were written (``status(runner)``: every
        few seconds)."""
        return self.runner.run(stop, frames=self.config.frames, status=status)

    def close(self) -> None:
        """The session closed (the board's counters read first when it streamed), then the
        outputs; safe after a failed open."""
        if self.runner is not None and self.session is not None and self.session.stream is not None:
            self.runner.refresh_device_counters()
        if self.session is not None:
            with contextlib.suppress(DeviceError):
                self.session.close()
        if self.sink is not None:
            with contextlib.suppress(BrokenPipeError, ValueError):
                self.sink.close()


def run(
    config: LiveConfig,
    *,
    on_record: Callable[[dict], None] | None = None,
    stop: threading.Event | None = None,
    in_slot=None,
) -> LiveStats:
    """Run a board: records to ``config``'s outputs and to ``on_record`` until ``stop`` is set
    or ``config.frames`` were written. Raises the project's errors (spiel_edge.errors): a
    ConfigError or InputError before the board is opened, DeviceError from it.
    ``in_slot``: as :class:`LiveRun` takes it."""
    live = LiveRun(config, in_slot=in_slot)
    stop = stop if stop is not None else threading.Event()
    try:
        live.prepare()
        live.open()
        live.start(stop)
        if on_record is not None:
            _tap(live.runner, on_record)
        return live.run(stop)
    finally:
        live.close()
        if live.tiers is not None:
            live.tiers.close(stop_compile=stop.is_set())
            live.tiers.leave()


def _tap(runner: LiveRunner, on_record: Callable[[dict], None]) -> None:
    """Each record handed to ``on_record`` after the outputs have it."""
    handle = runner.handle

    def handled(acq):
        record = handle(acq)
        on_record(record)
        return record

    runner.handle = handled
