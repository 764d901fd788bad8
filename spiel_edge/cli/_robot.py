"""`spiel-edge run --robot FILE`: its options mapped onto spiel_edge.robot.live's RobotConfig,
plus what is a terminal's (the signals, the Foxglove address, the summary, the exit status)."""

from __future__ import annotations

import contextlib
import sys
import threading

import click

from spiel_edge.cli import EXIT_OK, EXIT_PARTIAL
from spiel_edge.cli._signals import Finalizers, stop_on_signals
from spiel_edge.cli._status_line import say_live_views
from spiel_edge.robot.live import RobotConfig, RobotRun
from spiel_edge.safety.shown import shorten_tokens


def run_robot(
    robot_file: str,
    *,
    outputs: dict,
    frames: int | None,
    force: bool,
    association: str | None,
    max_targets: int | None,
    toa_correction: str | None,
    reconnect_timeout: float | None,
    track: bool,
    show_status: bool | None,
    realtime: int | None = None,
    odom_key: str | None = None,
) -> int:
    live = RobotRun(
        RobotConfig(
            robot_file,
            frames=frames,
            association=association,
            max_targets=max_targets,
            toa_correction=toa_correction,
            reconnect_timeout=reconnect_timeout,
            track=track,
            realtime=realtime,
            odom_key=odom_key,
            force=force,
            **outputs,
        )
    )
    try:
        live.prepare()  # the robot file, every file, every kernel, each board: before any opens
        live.open()
    except BaseException:
        live.close()
        raise
    say_live_views(live.sink)  # the Foxglove view's address, as `run` says it
    stop = threading.Event()
    finalizers = Finalizers()
    finalizers.add(live.sink.close_files)
    with stop_on_signals(stop, finalizers):
        try:
            live.run(stop)
        except BrokenPipeError:
            sys.stdout = None  # type: ignore[assignment]
        finally:
            finalizers.run_all()
            live.close()
            with contextlib.suppress(OSError):
                click.echo(shorten_tokens(live.runner.summary()), err=True)
    return EXIT_PARTIAL if live.sink.failed or live.dropped else EXIT_OK
