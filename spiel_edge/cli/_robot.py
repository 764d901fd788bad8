"""`spiel-edge run --robot FILE` (and the outputs `spiel-edge fuse` shares): thin over
spiel_edge.robot."""

from __future__ import annotations

import contextlib
import logging
import sys
import threading

import click
import numpy as np

from spiel_edge.cli import EXIT_OK, EXIT_PARTIAL
from spiel_edge.cli._signals import Finalizers, stop_on_signals
from spiel_edge.cli._status_line import say_live_views
from spiel_edge.outputs import check_outputs, open_outputs
from spiel_edge.outputs.fanout import check_output_key
from spiel_edge.robot.description import RobotSpec, load_robot
from spiel_edge.runtime.realtime import apply_realtime
from spiel_edge.safety.guard import FilePlan
from spiel_edge.safety.shown import shorten_tokens

log = logging.getLogger(__name__)


def robot_ros2(robot: RobotSpec, frame_id: str | None = None):
    """The fused records' ROS 2 settings: messages in the robot's frame (base_link, or odom
    when the fusion tracks in odom) in its own REP 103 axes, every board's mount on
    /tf_static; published targets limited by the boards' reach only (each board's field of
    view was applied by the fusion)."""
    from spiel_edge.messages.ros2_limits import SensorLimits
    from spiel_edge.outputs.ros2 import Ros2Settings, StaticTransform

    transforms = tuple(
        StaticTransform(
            robot.frame_id,
            b.name,
            tuple(float(v) / 1000.0 for v in b.mount.translation_mm),
            quaternion_from_matrix(b.mount.rotation),
        )
        for b in robot.boards
    )
    reach_m = robot.trigger.max_range_m + max(
        float(np.linalg.norm(b.mount.translation_mm)) / 1000.0 for b in robot.boards
    )
    limits = SensorLimits(2.0 * np.pi, 0.0, reach_m, (0.0, 0.0, 0.0))  # no boresight: all around
    return Ros2Settings(
        frame_id=frame_id or robot.frame_id, transforms=transforms, limits=limits, optical=False
    )


def quaternion_from_matrix(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a proper rotation matrix (Shepperd's method)."""
    m = np.asarray(r, float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = (0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s)
    n = float(np.linalg.norm(q))
    return tuple(float(v) / n for v in q)  # type: ignore[return-value]


def _prepare_kernels(robot: RobotSpec, association, max_targets) -> None:
    """Every board profile's kernels loaded (or compiled, with progress) in this thread, the
    tracker's included (the fusion always tracks)."""
    from spiel_edge.profile.schema import load_profile
    from spiel_edge.runtime.first_start import prepare_for_run

    for name in dict.fromkeys(b.profile for b in robot.boards):
        prepare_for_run(load_profile(name), association, max_targets, True, None)


def robot_inputs(plan: FilePlan, robot_file: str, robot: RobotSpec, option: str) -> None:
    """The robot file and every board's profile and calibration file noted as inputs of the
    command: no output may replace them, even with --force."""
    plan.input_if_file(robot_file, option)
    for b in robot.boards:
        plan.input_if_file(b.profile, f"board {b.name}'s profile")
        if b.calibration:
            plan.input_if_file(b.calibration, f"board {b.name}'s calibration")


def check_fused_outputs(plan: FilePlan, outputs: dict) -> dict:
    """The output files checked against the command's inputs (``plan``) and each other
    before any work: the outputs to open."""
    if outputs.get("zenoh") is not None:
        check_output_key(outputs["zenoh"], outputs.get("zenoh_encoding", "json"))
    return {**outputs, "record": check_outputs(plan, outputs["output"], outputs["record"])}


def open_fused_outputs(
    robot: RobotSpec, force: bool, outputs: dict, metadata: dict, odom: bool = False
):
    """The sinks of a fused run (NDJSON, MCAP, UDP, Foxglove, Zenoh) in the robot's frame
    (``odom`` when the fusion tracks in odom); ``outputs`` from :func:`check_fused_outputs`."""
    sink = open_outputs(
        outputs["output"],
        outputs["record"],
        outputs["udp"],
        outputs["foxglove"],
        outputs["zenoh"],
        metadata=metadata,
        force=force,
        record_profile=outputs.get("record_profile", "json"),
        zenoh_encoding=outputs.get("zenoh_encoding", "json"),
        ros2=robot_ros2(robot, "odom" if odom else None),
        zenoh_settings=outputs.get("zenoh_settings"),
    )
    say_live_views(sink)  # the Foxglove view's address, as `run` says it
    return sink


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
    from spiel_edge.robot.serve import RobotRunner

    robot = load_robot(robot_file)  # every problem of the file: one line, before any board
    plan = FilePlan(force)
    robot_inputs(plan, robot_file, robot, "--robot")
    outputs = check_fused_outputs(plan, outputs)
    # every kernel before any board opens: compiled in a board's thread, it holds the GIL for
    # seconds while the other boards' links fill, and their backlog reads as a clock jump
    _prepare_kernels(robot, association, max_targets)
    if realtime is not None:
        apply_realtime(realtime)
    sink = open_fused_outputs(
        robot,
        force,
        outputs,
        {
            "robot": robot.name,
            "robot_file": str(robot_file),
            "boards": ",".join(b.name for b in robot.boards),
        },
        odom=odom_key is not None,
    )
    stop = threading.Event()
    finalizers = Finalizers()
    finalizers.add(sink.close_files)
    try:
        runner = RobotRunner(
            robot,
            sink,
            association=association,
            max_targets=max_targets,
            toa_correction=toa_correction,
            reconnect_timeout=reconnect_timeout,
            track=track,
            odom_key=odom_key,
        )
    except BaseException:
        sink.close()
        raise
    with stop_on_signals(stop, finalizers):
        try:
            runner.run(stop, frames=frames)
        except BrokenPipeError:
            sys.stdout = None  # type: ignore[assignment]
        finally:
            finalizers.run_all()
            with contextlib.suppress(BrokenPipeError, ValueError):
                sink.close()
            with contextlib.suppress(OSError):
                click.echo(shorten_tokens(runner.summary()), err=True)
    dropped = any(w.stats.dropped for w in runner.workers)
    return EXIT_PARTIAL if sink.failed or dropped else EXIT_OK
