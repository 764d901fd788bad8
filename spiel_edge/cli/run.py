"""``spiel-edge run``: the pipeline on a board's live stream, records to every output asked."""

from __future__ import annotations

import contextlib
import sys
import threading

import click

from spiel_edge.cli import EXIT_OK, EXIT_PARTIAL
from spiel_edge.cli._options import (
    association_option,
    calibration_option,
    force_option,
    max_targets_option,
    port_option,
    profile_option,
    realtime_option,
    toa_correction_option,
)
from spiel_edge.cli._ros2 import ros2_options, zenoh_settings
from spiel_edge.cli._signals import Finalizers, stop_on_signals
from spiel_edge.cli._status_line import StatusLine, say_live_views
from spiel_edge.robot.slot_session import slot_starter
from spiel_edge.runtime.live import LiveConfig, LiveRun
from spiel_edge.runtime.loop import LiveRunner
from spiel_edge.safety.shown import escape, shorten_tokens
from spiel_edge.service.systemd import Notifier


@click.command("run")
@port_option
@click.option(
    "--robot",
    "robot_file",
    default=None,
    metavar="FILE",
    help="Serve every board of a robot description (a .toml or a built-in name such as "
    "virtual-4) from this process, fused in base_link (docs/robot.md); --port is not used.",
)
@click.option("--frames", type=click.IntRange(min=1), default=None, help="Stop after N records.")
@click.option(
    "--output", "-o", default="-", show_default=True, help="NDJSON file, or - for stdout."
)
@click.option(
    "--udp",
    multiple=True,
    metavar="HOST:PORT",
    help="Also send each record as a UDP datagram (repeatable).",
)
@click.option(
    "--record",
    type=click.Path(dir_okay=False),
    default=None,
    help="Also record raw acquisitions and records to FILE.mcap (strftime fields allowed).",
)
@click.option(
    "--foxglove",
    default=None,
    metavar="[HOST:]PORT",
    help="Live view for Foxglove (extra 'foxglove').",
)
@click.option(
    "--zenoh", default=None, metavar="KEY", help="Publish records on a Zenoh key (extra 'zenoh')."
)
@ros2_options
@profile_option
@calibration_option
@click.option(
    "--board-config/--no-board-config",
    "use_board",
    default=True,
    show_default=True,
    help="Use the geometry and acquisition settings stored on the board (`spiel-edge config`) "
    "over --profile; --calibration still overrides them.",
)
@association_option
@max_targets_option
@toa_correction_option
@click.option(
    "--rate",
    type=click.FloatRange(0, 10000),
    default=50.0,
    show_default=True,
    help="Acquisitions per second asked of the board (0: as fast as the link allows).",
)
@click.option(
    "--background",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="Target-free capture (.npy or spiel-csv frames file) to subtract; default: the one "
    "the virtual board sends, else none.",
)
@click.option(
    "--reconnect-timeout",
    type=click.FloatRange(min=0),
    default=None,
    help="Give up when the board stays away this many seconds (default: wait for it).",
)
@force_option
@click.option(
    "--track/--no-track",
    default=True,
    show_default=True,
    help="Track targets over acquisitions: records gain `tracks` and per target `track_id` "
    "(docs/tracking.md; [track] in the profile).",
)
@click.option(
    "--samples",
    type=click.Choice(["envelope", "iq"]),
    default="envelope",
    show_default=True,
    help="Sample format asked of the board: iq streams int16 I/Q pairs (protocol 2); the host "
    "computes the envelope and records the phase.",
)
@click.option(
    "--status/--no-status",
    "show_status",
    default=None,
    help="Status line on stderr every few seconds (default: when stderr is a terminal).",
)
@realtime_option
@click.option(
    "--odom",
    "odom_key",
    default=None,
    metavar="KEY",
    help="With --robot, track in odom: the robot's pose on this Zenoh key (expression), JSON "
    '{"stamp": s, "x": m, "y": m, "yaw": rad} or nav_msgs/Odometry from rmw_zenoh '
    "(docs/robot.md; extra 'zenoh').",
)
@click.option(
    "--slot",
    default=None,
    metavar="ROBOT:BOARD",
    help="Fire in this board's trigger slot of a robot file (e.g. rover.toml:front), on the "
    "clock the robot's computers share (chrony/PTP): boards in earshot served by different "
    "processes take turns (docs/robot.md). Needs protocol 2; the rate is the robot's.",
)
def command(
    port,
    robot_file,
    frames,
    output,
    udp,
    record,
    foxglove,
    zenoh,
    profile_name,
    calibration,
    use_board,
    association,
    max_targets,
    toa_correction,
    rate,
    background,
    reconnect_timeout,
    force,
    track,
    samples,
    show_status,
    realtime,
    odom_key,
    slot,
    **ros2,
) -> int:
    """Stream from the board and write one record per acquisition (NDJSON on stdout by default).

    The geometry is, by precedence: --calibration, else the config stored on the board (unless
    --no-board-config), else --profile. Unplugging the board does not stop the command: it
    waits for the same board to come back and streams again. SIGINT or SIGTERM stops the
    stream and exits cleanly; SIGINT, SIGTERM or SIGHUP finalize the outputs within 1 s.
    """
    if slot and robot_file:
        raise click.UsageError("--slot is for one board's process; --robot schedules its boards")
    if robot_file:  # several boards, fused (spiel_edge/robot)
        from spiel_edge.cli._robot import run_robot

        _refuse_per_board_options()
        outputs = dict(output=output, record=record, udp=udp, foxglove=foxglove, zenoh=zenoh)
        outputs.update(
            record_profile=ros2["record_profile"],
            zenoh_encoding=ros2["zenoh_encoding"],
            zenoh_settings=zenoh_settings(ros2),
        )
        return run_robot(
            robot_file,
            outputs=outputs,
            frames=frames,
            force=force,
            association=association,
            max_targets=max_targets,
            toa_correction=toa_correction,
            reconnect_timeout=reconnect_timeout,
            track=track,
            show_status=show_status,
            realtime=realtime,
            odom_key=odom_key,
        )
    if odom_key:
        raise click.UsageError("--odom goes with --robot (one board tracks in its own frame)")
    in_slot = slot_starter(slot) if slot else None  # the robot file: before the board
    source = click.get_current_context().get_parameter_source("rate")
    if in_slot is not None and source == click.core.ParameterSource.COMMANDLINE:
        raise click.UsageError("--rate with --slot: the slot's rate is the robot file's period")
    config = LiveConfig(
        port=port or None,
        frames=frames,
        profile=profile_name,
        calibration=calibration,
        use_board=use_board,
        association=association,
        max_targets=max_targets,
        toa_correction=toa_correction,
        rate=rate,
        background=background,
        reconnect_timeout=reconnect_timeout,
        track=track,
        samples=samples,
        slot=slot,
        realtime=realtime,
        output=output,
        record=record,
        udp=udp,
        foxglove=foxglove,
        zenoh=zenoh,
        force=force,
        ros2=ros2,
    )
    notifier = Notifier()
    live = LiveRun(config, notifier=notifier, in_slot=in_slot)
    live.prepare()  # every file, the profile, the ToA correction, the kernels: before the board
    port, tiers, session = live.port, live.tiers, live.session
    if show_status is None:
        show_status = sys.stderr.isatty()
    stop = threading.Event()
    finalizers = Finalizers()
    if tiers is not None:  # a signal stops the background compile; a normal end leaves it
        finalizers.add(lambda: _say(tiers.close(stop_compile=stop.is_set())))
    with stop_on_signals(stop, finalizers):
        try:
            live.open()
            finalizers.add(live.sink.close_files)
            say_live_views(live.sink)
            session.on_waiting = lambda waited: _still_waiting(notifier, port, waited)
            live.start(stop)
            if live.slotted is not None:
                slotted = live.slotted
                finalizers.add(lambda: click.echo(shorten_tokens(slotted.summary()), err=True))
            notifier.ready(f"streaming from {port}")
            live.run(stop, status=_reporter(show_status, notifier))
        except BrokenPipeError:  # the reader of stdout went away (| head): a normal end
            sys.stdout = None  # type: ignore[assignment]  # nothing more can be flushed there
        finally:
            notifier.stopping()
            finalizers.run_all()  # the files first: closing the session can take a while
            _close(live, show_status)
    if tiers is not None:  # the dispatchers back, once nothing runs (a run in-process)
        tiers.leave()
    sink, runner = live.sink, live.runner
    failed = sink is not None and sink.failed
    if failed:
        click.echo(f"outputs that failed: {escape('; '.join(sink.failed))}", err=True)
    return EXIT_PARTIAL if failed or (runner is not None and runner.stats.errors) else EXIT_OK


def _say(line: str | None) -> None:
    if line:
        with contextlib.suppress(OSError):
            click.echo(line, err=True)


def _still_waiting(notifier: Notifier, port: str, waited: float) -> None:
    notifier.ping()
    notifier.status(f"waiting {waited:.0f} s for the board at {port} to come back")


STATUS = StatusLine()


def _reporter(show_status: bool, notifier: Notifier):
    if not show_status and not notifier.enabled:
        return None

    def report(runner: LiveRunner) -> None:
        line = runner.status_line()
        notifier.status(line)
        if show_status:
            STATUS.show(line)  # a log record clears it first, never joins it

    return report


def _close(live: LiveRun, show_status: bool) -> None:
    runner = live.runner
    streamed = live.session.stream is not None  # a stream was started: its summary says how
    live.close()  # the board's counters, the session, then the outputs
    with contextlib.suppress(OSError):  # stderr may be a terminal that hung up
        if show_status:
            STATUS.close()
        if runner is not None and (runner.stats.records or streamed):
            click.echo(shorten_tokens(runner.summary()), err=True)


# one board's options: with --robot each board's come from the robot file
PER_BOARD_OPTIONS = (
    "profile_name",
    "calibration",
    "use_board",
    "rate",
    "background",
    "samples",
    "frame_id",
    "parent_frame",
    "translation_m",
    "rotation_rpy_deg",
    "rotation_xyzw",
    "static_tf",
)


def _refuse_per_board_options() -> None:
    """UsageError for a one-board option given with --robot (it would be ignored)."""
    ctx = click.get_current_context()
    for param in ctx.command.params:
        if param.name not in PER_BOARD_OPTIONS:
            continue
        if ctx.get_parameter_source(param.name) == click.core.ParameterSource.COMMANDLINE:
            why = (
                "the rate is the robot file's trigger period"
                if param.name == "rate"
                else "each board's settings are in the robot file (docs/robot.md)"
            )
            raise click.UsageError(f"{param.opts[0]} is one board's option: with --robot {why}")
