"""ROS 2 messages in CDR (little-endian XCDR1, as rosbag2 and DDS carry them), with ``struct``.

No rclpy, no rosbags at run time: a message is the 4-byte encapsulation header
``00 01 00 00`` then the fields, each aligned to its size from the start of the fields.
The layouts that do not change with the data are packed once (``struct.Struct`` per frame id),
so a PointStamped costs about one ``pack`` call (52 bytes for the frame id ``spiel``).

Read back: spiel_msgs/msg/Acquisition (:func:`decode_acquisition`), std_msgs/msg/String
(:func:`decode_string`) and the planar pose of a nav_msgs/msg/Odometry (:func:`decode_odometry`,
either byte order).

Messages: geometry_msgs/msg/PointStamped, sensor_msgs/msg/PointCloud2 (the targets, with
the covariance's upper triangle),
tf2_msgs/msg/TFMessage (the static transform), std_msgs/msg/String (the JSON record), and
spiel_msgs/msg/Acquisition (raw frames; read back by :func:`decode_acquisition`).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.messages.ros2_types import rosbag2_definition

ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR_LE

POINT_STAMPED = "geometry_msgs/msg/PointStamped"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"
ACQUISITION = "spiel_msgs/msg/Acquisition"
ODOMETRY = "nav_msgs/msg/Odometry"

# the point layout of /spiel/targets: (name, PointField datatype, offset); FLOAT32=7, INT32=5
TARGET_FIELDS = (
    ("x", 7, 0),
    ("y", 7, 4),
    ("z", 7, 8),
    ("score", 7, 12),
    ("track_id", 5, 16),  # -1: no track
    ("cov_xx", 7, 20),  # the covariance's upper triangle, m^2
    ("cov_xy", 7, 24),
    ("cov_xz", 7, 28),
    ("cov_yy", 7, 32),
    ("cov_yz", 7, 36),
    ("cov_zz", 7, 40),
)
_TARGET_POINT = struct.Struct("<4fi6f")
_NO_COVARIANCE = (math.nan,) * 6
_STEP = _TARGET_POINT.size
_CLOUD_TAIL = struct.Struct("<?3xIII")  # is_bigendian, point_step, row_step, data length


def stamp_of(seconds: float | None) -> tuple[int, int]:
    """builtin_interfaces/Time (sec, nanosec) from Unix seconds (0, 0 when unknown).

    Microsecond resolution: a float of today's Unix seconds holds no more (records carry
    ``host_time`` rounded to the microsecond)."""
    try:
        sec = int(seconds)  # type: ignore[arg-type]  # split first: seconds * 1e9 loses ~100 ns
    except (TypeError, ValueError, OverflowError):  # None, NaN, infinity
        return 0, 0
    if sec < 0:
        return 0, 0
    micro = round((seconds - sec) * 1e6)  # type: ignore[operator]
    return (sec + 1, 0) if micro >= 1_000_000 else (sec, micro * 1000)


class _Writer:
    """Generic CDR writer for the messages built once (templates, transforms, acquisitions)."""

    def __init__(self) -> None:
        self.buf = bytearray()

    def align(self, size: int) -> None:
        self.buf += b"\x00" * (-len(self.buf) % size)

    def put(self, fmt: str, *values: object) -> None:
        self.align(struct.calcsize("<" + fmt.lstrip("0123456789")[0]))
        self.buf += struct.pack("<" + fmt, *values)

    def string(self, text: str) -> None:
        raw = text.encode("utf-8") + b"\x00"
        self.put("I", len(raw))
        self.buf += raw

    def header(self, sec: int, nanosec: int, frame_id: str) -> None:
        self.put("iI", sec, nanosec)
        self.string(frame_id)


@dataclass(frozen=True)
class StaticTransform:
    """The pose of the sensor frame (child) in a robot frame (parent): metres, unit quaternion."""

    parent: str
    child: str
    translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)


class Ros2Encoder:
    """Encoders for one sensor frame id; the fixed parts are packed once here."""

    def __init__(self, frame_id: str = "spiel"):
        if not frame_id or "\x00" in frame_id:
            raise ValueError(f"frame id {frame_id!r} must be a non-empty string without NUL")
        self.frame_id = frame_id
        raw = frame_id.encode("utf-8") + b"\x00"
        pad = -(12 + len(raw)) % 8  # stamp (8) + length (4) + text, then float64 alignment
        self._point = struct.Struct(f"<4siII{len(raw)}s{pad}x3d")
        self._raw = raw
        # PointCloud2: header and size, the fixed field list (from a 4-aligned offset), the rest
        head_pad = -(12 + len(raw)) % 4
        self._cloud_head = struct.Struct(f"<4siII{len(raw)}s{head_pad}xII")
        fields = _Writer()
        fields.put("I", len(TARGET_FIELDS))
        for name, datatype, offset in TARGET_FIELDS:
            fields.string(name)
            fields.put("I", offset)
            fields.put("B", datatype)
            fields.put("I", 1)
        fields.align(4)
        self._cloud_fields = bytes(fields.buf)  # position-independent: every part 4-aligned

    def point_stamped(self, position_mm, stamp_s: float | None) -> bytes:
        """geometry_msgs/msg/PointStamped, metres."""
        sec, nanosec = stamp_of(stamp_s)
        x, y, z = position_mm
        return self._point.pack(
            ENCAPSULATION, sec, nanosec, len(self._raw), self._raw, x / 1e3, y / 1e3, z / 1e3
        )

    def targets_cloud(self, targets: list[dict], stamp_s: float | None) -> bytes:
        """sensor_msgs/msg/PointCloud2, one point per target (TARGET_FIELDS), metres."""
        sec, nanosec = stamp_of(stamp_s)
        data = b"".join([_target_point(t) for t in targets])
        count = len(targets)
        raw = self._raw
        return b"".join(
            (
                self._cloud_head.pack(ENCAPSULATION, sec, nanosec, len(raw), raw, 1, count),
                self._cloud_fields,
                _CLOUD_TAIL.pack(False, _STEP, _STEP * count, len(data)),
                data,
                b"\x01",  # is_dense: no invalid points
            )
        )

    def tf_message(self, transforms: list[StaticTransform], stamp_s: float | None) -> bytes:
        """tf2_msgs/msg/TFMessage (for /tf_static)."""
        sec, nanosec = stamp_of(stamp_s)
        w = _Writer()
        w.put("I", len(transforms))
        for tf in transforms:
            w.header(sec, nanosec, tf.parent)
            w.string(tf.child)
            w.put("3d", *tf.translation_m)
            w.put("4d", *tf.rotation_xyzw)
        return ENCAPSULATION + bytes(w.buf)


def _target_point(target: dict) -> bytes:
    x, y, z = target["position_mm"]
    cov = target.get("covariance_mm2")
    track = target.get("track_id")
    score = target.get("score")
    upper = (
        (cov[0][0] / 1e6, cov[0][1] / 1e6, cov[0][2] / 1e6)
        + (cov[1][1] / 1e6, cov[1][2] / 1e6, cov[2][2] / 1e6)
        if cov
        else _NO_COVARIANCE
    )
    return _TARGET_POINT.pack(
        x / 1e3,
        y / 1e3,
        z / 1e3,
        math.nan if score is None else score,
        -1 if track is None else track,
        *upper,
    )


def string_message(text: str) -> bytes:
    """std_msgs/msg/String."""
    raw = text.encode("utf-8") + b"\x00"
    return ENCAPSULATION + struct.pack("<I", len(raw)) + raw


def decode_string(data: bytes) -> str:
    """The text of a std_msgs/msg/String (little-endian CDR); InputError when malformed."""
    if bytes(data[:4]) != ENCAPSULATION:
        raise InputError(f"not little-endian CDR (header {bytes(data[:4]).hex()})")
    try:
        (length,) = struct.unpack_from("<I", data, 4)
    except struct.error as exc:
        raise InputError(f"truncated String message: {exc}") from exc
    raw = bytes(data[8 : 8 + length])
    if length == 0 or len(raw) != length or raw[-1:] != b"\x00":
        raise InputError(f"String message of {len(raw)} bytes where {length} are announced")
    try:
        return raw[:-1].decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"String message not UTF-8: {exc}") from exc


def acquisition_message(
    frames: np.ndarray, *, seq: int, device_time_us: int, stamp_s: float | None
) -> bytes:
    """spiel_msgs/msg/Acquisition: raw frames as float64 (counts; NaN for a missing sample)."""
    frames = np.ascontiguousarray(frames, dtype="<f8")
    if frames.ndim != 2:
        raise ValueError(f"frames must be channels x samples, got shape {frames.shape}")
    w = _Writer()
    w.header(*stamp_of(stamp_s), "spiel")
    w.put("q", int(seq))
    w.put("q", int(device_time_us))
    w.put("II", *frames.shape)
    w.put("I", frames.size)
    w.align(8)
    return ENCAPSULATION + bytes(w.buf) + frames.tobytes()


def decode_acquisition(data: bytes) -> tuple[int, np.ndarray]:
    """(seq, frames) of a spiel_msgs/msg/Acquisition; InputError when malformed."""
    try:
        if data[:4] != ENCAPSULATION:
            raise InputError(f"not little-endian CDR (header {data[:4].hex()})")
        body = memoryview(data)[4:]
        (length,) = struct.unpack_from("<I", body, 8)
        pos = 12 + length
        pos += -pos % 8
        seq, _device_time, channels, samples, count = struct.unpack_from("<qqIII", body, pos)
        pos += 28
        pos += -pos % 8
        if count != channels * samples or len(body) < pos + 8 * count:
            raise InputError(f"frames of {count} values for {channels} x {samples}")
        frames = np.frombuffer(body, "<f8", count, pos).reshape(channels, samples)
    except struct.error as exc:
        raise InputError(f"truncated Acquisition message: {exc}") from exc
    return seq, frames.astype(np.float64)


def decode_odometry(data: bytes) -> tuple[float, float, float, float]:
    """(stamp s, x m, y m, yaw rad) of a nav_msgs/msg/Odometry in CDR (either byte order):
    its header's stamp and its pose's position and heading (the rest is not read);
    InputError when malformed."""
    try:
        order = {b"\x00\x01": "<", b"\x00\x00": ">"}.get(bytes(data[:2]))
        if order is None:
            raise InputError(f"not CDR (header {bytes(data[:4]).hex()})")
        body = memoryview(data)[4:]
        sec, nanosec = struct.unpack_from(order + "iI", body, 0)
        pos = 8
        for _ in range(2):  # header.frame_id, child_frame_id: length (with the NUL), bytes
            pos += -pos % 4
            (length,) = struct.unpack_from(order + "I", body, pos)
            pos += 4 + length
        pos += -pos % 8
        x, y, _z, qx, qy, qz, qw = struct.unpack_from(order + "7d", body, pos)
    except struct.error as exc:
        raise InputError(f"truncated Odometry message: {exc}") from exc
    if not all(math.isfinite(v) for v in (x, y, qx, qy, qz, qw)):
        raise InputError("Odometry pose not finite")
    yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return sec + nanosec * 1e-9, x, y, yaw


# message definitions stored in the MCAP (schema encoding ros2msg), as rosbag2 writes them
DEFINITIONS = {
    name: rosbag2_definition(name)
    for name in (POINT_STAMPED, POINT_CLOUD2, TF_MESSAGE, STRING, ACQUISITION)
}
