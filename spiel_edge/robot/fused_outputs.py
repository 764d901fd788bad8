"""The outputs of a fused run (`run --robot` and `fuse` share them): the command's inputs
noted so no output replaces them, the output files checked before any work, and the sinks
opened in the robot's frame with every board's mount on /tf_static."""

from __future__ import annotations

import numpy as np

from spiel_edge.outputs import check_outputs, open_outputs
from spiel_edge.outputs.fanout import check_output_key
from spiel_edge.robot.description import RobotSpec
from spiel_edge.safety.guard import FilePlan


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
    return open_outputs(
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
