"""Run a robot's boards, fused: the one place `run --robot` is assembled (issue 42), for the
CLI and for a library user, as runtime/live.py is for one board.

A :class:`RobotConfig` says what to run; :class:`RobotRun` does it in steps, each once:
``prepare`` (the robot file read, every input and output file checked, every board's kernels
ready, each board prepared as `run` prepares one: before any board opens), ``open`` (the
outputs), ``run`` and ``close``. :func:`run` is the whole of it::

    from spiel_edge.robot.live import RobotConfig, run

    records = []
    run(RobotConfig("virtual-4", frames=20, output=None), on_record=records.append)

The CLI (cli/_robot.py) maps its options onto a RobotConfig and adds what is a terminal's:
the signals, the Foxglove address, the summary and the exit status.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from dataclasses import dataclass

from spiel_edge.outputs import Sink
from spiel_edge.robot.description import RobotSpec, load_robot
from spiel_edge.robot.fused_outputs import check_fused_outputs, open_fused_outputs, robot_inputs
from spiel_edge.runtime.realtime import apply_realtime
from spiel_edge.safety.guard import FilePlan


@dataclass(frozen=True)
class RobotConfig:
    """What one robot's fused run is (the options of `spiel-edge run --robot`, docs/robot.md)."""

    robot: str  # a robot file, or a built-in robot's name (virtual-4)
    frames: int | None = None  # stop after this many fused records (None: until stopped)
    association: str | None = None
    max_targets: int | None = None
    toa_correction: str | None = None  # None: chosen per board as `run` chooses it
    reconnect_timeout: float | None = None
    track: bool = True
    realtime: int | None = None
    odom_key: str | None = None  # track in odom with the robot's pose from this Zenoh key
    # outputs: NDJSON file or "-" (None: none), MCAP recording, UDP, Foxglove, Zenoh
    output: str | None = "-"
    record: str | None = None
    udp: tuple[str, ...] = ()
    foxglove: str | None = None
    zenoh: str | None = None
    record_profile: str = "json"
    zenoh_encoding: str = "json"
    zenoh_settings: object = None  # outputs.ros2.ZenohSettings: where --zenoh publishes
    force: bool = False  # outputs may replace files (never an input)

    def outputs(self) -> dict:
        return {
            "output": self.output,
            "record": self.record,
            "udp": self.udp,
            "foxglove": self.foxglove,
            "zenoh": self.zenoh,
            "record_profile": self.record_profile,
            "zenoh_encoding": self.zenoh_encoding,
            "zenoh_settings": self.zenoh_settings,
        }


class RobotRun:
    """One robot's fused run: ``prepare()``, ``open()``, ``run(stop)``, ``close()``."""

    def __init__(self, config: RobotConfig):
        self.config = config
        self.robot: RobotSpec | None = None
        self.sink = None
        self.runner = None  # robot/serve.py's RobotRunner, once prepared
        self._outputs: dict = {}

    def prepare(self) -> None:
        """Before any board: the robot file (every problem of it in one line), every input
        and output file, every board's kernels (compiled in a board's thread they would hold
        the GIL for seconds while the other boards' links fill, and the backlog reads as a
        clock jump) and each board prepared (robot/board_worker.py)."""
        from spiel_edge.robot.serve import RobotRunner

        c = self.config
        self.robot = load_robot(c.robot)
        plan = FilePlan(c.force)
        robot_inputs(plan, c.robot, self.robot, "--robot")
        self._outputs = check_fused_outputs(plan, c.outputs())
        _prepare_kernels(self.robot, c.association, c.max_targets)
        apply_realtime(c.realtime)
        self.runner = RobotRunner(
            self.robot,
            Sink(),  # the outputs come in open()
            association=c.association,
            max_targets=c.max_targets,
            toa_correction=c.toa_correction,
            reconnect_timeout=c.reconnect_timeout,
            track=c.track,
            odom_key=c.odom_key,
        )

    def open(self) -> None:
        """The outputs, in the robot's frame (odom when it tracks in odom)."""
        c, robot = self.config, self.robot
        if c.output is None and not (c.record or c.udp or c.foxglove or c.zenoh):
            self.sink = Sink()  # a library run: records go to on_record only
        else:
            metadata = {
                "robot": robot.name,
                "robot_file": str(c.robot),
                "boards": ",".join(b.name for b in robot.boards),
            }
            self.sink = open_fused_outputs(
                robot, c.force, self._outputs, metadata, odom=c.odom_key is not None
            )
        self.runner.sink = self.sink

    def run(self, stop: threading.Event) -> int:
        """Fused records until ``stop`` or ``frames`` of them; DeviceError when no board is
        left. Returns the records written."""
        return self.runner.run(stop, frames=self.config.frames)

    @property
    def dropped(self) -> bool:
        return self.runner is not None and any(w.stats.dropped for w in self.runner.workers)

    def close(self) -> None:
        """The outputs closed; safe after a failed open."""
        if self.runner is not None:
            self.runner.close_odometry()
        if self.sink is not None:
            with contextlib.suppress(BrokenPipeError, ValueError):
                self.sink.close()


def run(
    config: RobotConfig,
    *,
    on_record: Callable[[dict], None] | None = None,
    stop: threading.Event | None = None,
) -> RobotRun:
    """Run a robot's boards, fused: records to ``config``'s outputs and to ``on_record`` until
    ``stop`` is set or ``config.frames`` were written. Raises the project's errors
    (spiel_edge.errors): a ConfigError or InputError before any board opens, DeviceError when
    no board is left. Returns the finished :class:`RobotRun` (``runner.summary()``)."""
    live = RobotRun(config)
    try:
        live.prepare()
        live.open()
        live.runner.on_record = on_record
        live.run(stop if stop is not None else threading.Event())
    finally:
        live.close()
    return live


def _prepare_kernels(robot: RobotSpec, association, max_targets) -> None:
    """Every board profile's kernels loaded (or compiled, with progress) in this thread, the
    tracker's included (the fusion always tracks)."""
    from spiel_edge.profile.schema import load_profile
    from spiel_edge.runtime.first_start import prepare_for_run

    for name in dict.fromkeys(b.profile for b in robot.boards):
        prepare_for_run(load_profile(name), association, max_targets, True, None)
