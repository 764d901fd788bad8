"""``spiel-edge fuse``: the targets of several boards' processes, fused, over Zenoh."""

from __future__ import annotations

import contextlib
import sys
import threading

import click

from spiel_edge.cli import EXIT_OK, EXIT_PARTIAL
from spiel_edge.cli._options import force_option, realtime_option
from spiel_edge.cli._signals import Finalizers, stop_on_signals
from spiel_edge.runtime.tiered import tiered_work
from spiel_edge.safety.shown import shorten_tokens


@click.command("fuse")
@click.option(
    "--robot",
    "robot_file",
    required=True,
    metavar="FILE",
    help="Robot description (.toml, or a built-in name): the boards, their Zenoh keys and mounts.",
)
@click.option("--frames", type=click.IntRange(min=1), default=None, help="Stop after N records.")
@click.option(
    "--idle",
    type=click.FloatRange(min=0.1),
    default=None,
    help="Stop after this many seconds without a board record, once records came (default: wait).",
)
@click.option(
    "--output", "-o", default="-", show_default=True, help="NDJSON file, or - for stdout."
)
@click.option("--udp", multiple=True, metavar="HOST:PORT", help="Also send each record by UDP.")
@click.option("--record", type=click.Path(dir_okay=False), default=None, help="Also to FILE.mcap.")
@click.option(
    "--foxglove", default=None, metavar="[HOST:]PORT", help="Live view (extra 'foxglove')."
)
@click.option("--zenoh", default=None, metavar="KEY", help="Publish the fused records on KEY too.")
@click.option(
    "--record-profile",
    type=click.Choice(["json", "ros2"]),
    default="json",
    show_default=True,
    help="MCAP encoding of --record: json (Foxglove) or ros2 (CDR, read by rosbags, ros2 bag).",
)
@click.option(
    "--zenoh-encoding",
    type=click.Choice(["json", "cdr"]),
    default="json",
    show_default=True,
    help="Encoding of the fused records published on Zenoh: JSON or ROS 2 CDR.",
)
@click.option(
    "--connect",
    multiple=True,
    metavar="ENDPOINT",
    help="Zenoh endpoint to connect to, e.g. "
    "tcp/192.168.1.2:7447 (a router, or a peer); repeatable.",
)
@click.option(
    "--listen", multiple=True, metavar="ENDPOINT", help="Zenoh endpoint to listen on; repeatable."
)
@click.option(
    "--mode",
    type=click.Choice(["peer", "client"]),
    default=None,
    help="Zenoh mode (default: the configuration's, peer).",
)
@click.option(
    "--zenoh-config",
    default=None,
    metavar="FILE",
    help="Zenoh JSON5 configuration (default: $ZENOH_CONFIG, else Zenoh's defaults).",
)
@click.option(
    "--odom",
    "odom_key",
    default=None,
    metavar="KEY",
    help="Track in odom: the robot's pose on this Zenoh key (expression), JSON "
    '{"stamp": s, "x": m, "y": m, "yaw": rad} or a ROS 2 nav_msgs/Odometry from rmw_zenoh '
    "(e.g. '*/odom/**').",
)
@click.option(
    "--replay",
    "replay",
    multiple=True,
    metavar="BOARD=FILE",
    help="Offline instead of Zenoh: the board's records as its `run -o` wrote them (NDJSON); "
    "repeat per board (boards without a file are left out).",
)
@click.option(
    "--odom-file",
    type=click.Path(dir_okay=False),
    default=None,
    help="With --replay, track in odom with a recording's poses: an MCAP (rosbag2 "
    "nav_msgs/Odometry, or JSON messages) or NDJSON of the JSON message.",
)
@click.option(
    "--odom-topic", default="/odom", show_default=True, help="The --odom-file MCAP's topic."
)
@click.option("--track/--no-track", default=True, show_default=True, help="One tracker over all.")
@force_option
@realtime_option
def command(
    robot_file,
    frames,
    idle,
    output,
    udp,
    record,
    foxglove,
    zenoh,
    record_profile,
    zenoh_encoding,
    connect,
    listen,
    mode,
    zenoh_config,
    odom_key,
    replay,
    odom_file,
    odom_topic,
    track,
    force,
    realtime,
) -> int:
    """Subscribe to every board of a robot on Zenoh (each published by its own `spiel-edge run
    --zenoh KEY`, on this computer or another) and write their targets fused in the robot's
    frame, one record per trigger cycle (docs/robot.md). With --replay, the boards' recorded
    records instead, offline (no Zenoh)."""
    from spiel_edge.robot.description import load_robot
    from spiel_edge.robot.fused_outputs import check_fused_outputs, robot_inputs
    from spiel_edge.safety.guard import FilePlan

    robot = load_robot(robot_file)
    plan = FilePlan(force)
    robot_inputs(plan, robot_file, robot, "--robot")
    outputs = dict(
        output=output,
        record=record,
        udp=udp,
        foxglove=foxglove,
        zenoh=zenoh,
        record_profile=record_profile,
        zenoh_encoding=zenoh_encoding,
    )
    live = dict(connect=connect, listen=listen, mode=mode, zenoh_config=zenoh_config, odom=odom_key)
    if replay:
        live.update(frames=frames, idle=idle, realtime=realtime)
        given = [f"--{k.replace('_', '-')}" for k, v in live.items() if v]
        if given:
            raise click.UsageError(f"{given[0]} is for the live fusion, not with --replay")
        return _replay(robot, replay, odom_file, odom_topic, track, plan, outputs)
    if odom_file:
        raise click.UsageError("--odom-file goes with --replay (live odometry: --odom KEY)")
    outputs = check_fused_outputs(plan, outputs)
    if connect or mode or zenoh_config:  # the fused records go out the way the boards' come in
        from spiel_edge.outputs.ros2 import ZenohSettings

        outputs["zenoh_settings"] = ZenohSettings(
            mode=mode or "", connect=tuple(connect), config_file=zenoh_config
        )
    from spiel_edge.robot.zenoh_fuse import ZenohFuse, verifiers
    from spiel_edge.robot.zenoh_fuse import zenoh_config as make_config

    verifiers(robot)  # a bad auth_key_file: one line, before any output is opened
    config = make_config(connect, listen, mode, zenoh_config)
    if realtime is not None:  # the tracker's kernels first, then Zenoh's threads inherit it
        from spiel_edge.runtime.realtime import apply_realtime
        from spiel_edge.track import Tracker

        Tracker(robot.track_spec()).update([], 0.0)
        apply_realtime(realtime)
    meta = {"robot": robot.name, "fused_over": "zenoh"}
    sink = _open_outputs(robot, force, outputs, meta, odom=odom_key is not None)
    stop = threading.Event()
    finalizers = Finalizers()
    finalizers.add(sink.close_files)
    fuse = None
    # the tracker's kernels missing: it runs interpreted while they compile in the background
    # (not with --realtime: its threads are set up after they are compiled, above)
    exercise = _tracker_exercise(robot) if track and realtime is None else None
    with (
        tiered_work(None, what="fuse", exercise=exercise, stopped=stop.is_set),
        stop_on_signals(stop, finalizers),
    ):
        try:
            fuse = ZenohFuse(robot, sink, config=config, track=track, odom_key=odom_key)
            fuse.run(stop, frames=frames, idle_s=idle)
        except BrokenPipeError:
            sys.stdout = None  # type: ignore[assignment]
        finally:
            finalizers.run_all()
            if fuse is not None:
                fuse.close()
            _close_and_summarise(sink, fuse)
    return _status(sink, fuse)


def _replay(robot, items, odom_file, odom_topic, track, plan, outputs) -> int:
    """``fuse --replay``: every input read and checked before the outputs open."""
    from spiel_edge.robot.fused_outputs import check_fused_outputs
    from spiel_edge.robot.odometry_sources import read_odometry_file
    from spiel_edge.robot.record_fuse import read_replay
    from spiel_edge.robot.record_fuse import replay as fuse_replay

    files = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise click.UsageError(f"--replay {item!r}: BOARD=FILE, e.g. front=front.ndjson")
        if name in files:
            raise click.UsageError(f"--replay: board {name!r} given twice")
        files[name] = path
        plan.input_if_file(path, f"--replay {name}")
    if odom_file:
        plan.input_if_file(odom_file, "--odom-file")
    outputs = check_fused_outputs(plan, outputs)
    streams = read_replay(robot, files)
    odometry = read_odometry_file(odom_file, odom_topic) if odom_file else None
    meta = {"robot": robot.name, "fused_over": "replay", "replayed": ",".join(sorted(files))}
    sink = _open_outputs(robot, plan.force, outputs, meta, odom=odometry is not None)
    fuse = None
    exercise = _tracker_exercise(robot) if track else None
    try:
        with tiered_work(None, what="fuse", exercise=exercise):
            fuse = fuse_replay(robot, sink, streams, track=track, odometry=odometry, boards=files)
    except BrokenPipeError:
        sys.stdout = None  # type: ignore[assignment]
    finally:
        _close_and_summarise(sink, fuse)
    return _status(sink, fuse)


def _open_outputs(robot, force: bool, outputs: dict, metadata: dict, odom: bool):
    """The fused run's outputs (robot/fused_outputs.py, as `run --robot` opens them), and the
    Foxglove view's address said."""
    from spiel_edge.cli._status_line import say_live_views
    from spiel_edge.robot.fused_outputs import open_fused_outputs

    sink = open_fused_outputs(robot, force, outputs, metadata, odom=odom)
    say_live_views(sink)
    return sink


def _tracker_exercise(robot):
    """What fuse compiles: the tracker's step (``FusedCycle`` runs it once at its start)."""

    def exercise() -> None:
        from spiel_edge.track import Tracker

        Tracker(robot.track_spec()).update([], 0.0)

    return exercise


def _close_and_summarise(sink, fuse) -> None:
    with contextlib.suppress(BrokenPipeError, ValueError):
        sink.close()
    if fuse is not None:
        with contextlib.suppress(OSError):
            click.echo(shorten_tokens(fuse.summary()), err=True)


def _status(sink, fuse) -> int:
    """Partial when an output failed, a board was dropped or a forged record came."""
    failed = bool(sink.failed) or (
        fuse is not None and bool(fuse.dropped or getattr(fuse, "forged", 0))
    )
    return EXIT_PARTIAL if failed else EXIT_OK
