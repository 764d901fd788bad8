"""The ROS 2 messages of a record, one set for every ROS 2 output (ros2 MCAP, Zenoh bridge
keys, rmw_zenoh, Foxglove): what is published, in which frame, on which topic.

Per record (topics relative to the prefix, ``spiel`` by default):

* ``point``: geometry_msgs/PointStamped, the best published target;
* ``targets``: sensor_msgs/PointCloud2 of the published targets: x y z, score, track_id
  (-1: none), and the covariance's six upper-triangle entries cov_xx cov_xy cov_xz cov_yy
  cov_yz cov_zz (m^2), float32 little-endian, point_step 44;
* ``tracks``: radar_msgs/RadarTracks, the confirmed tracks (uuid from the track id,
  position, velocity, upper-triangle position and velocity covariances; acceleration and size
  unknown: NaN covariance, zero vectors);
* ``range``: sensor_msgs/Range (ULTRASOUND) of the nearest published target with the board's
  field of view and range limits (+inf: nothing in range, REP 117); a one- or two-transducer
  board's record gives its own ``range_mm`` and ``range_var_mm2`` (pipeline/ranging.py);
* ``/diagnostics``: diagnostic_msgs/DiagnosticArray, once per second of record time: the
  session's counters and the board's state (``status_provider``), else the record counts;
* ``/tf_static``: tf2_msgs/TFMessage, the mount and the optical frame (below).

Frames (REP 103): ``frame_id`` (default ``spiel``) is the sensor's body frame, x along the
boresight, y left, z up, and is what the mount places on the robot. The board's geometry has
z along the boresight, x right and y down when looking along it: that is the optical
convention, so the messages are stamped ``<frame_id>_optical`` and ``/tf_static`` carries the
fixed rotation ``frame_id -> <frame_id>_optical`` (as cameras do) besides the mount.

What is published (:class:`TargetFilter`): a target with a finite position and covariance,
score >= MIN_SCORE, inside the field of view (angle from the boresight below half of it) and
between the range limits (within RANGE_MARGIN_M), with no variance above MAX_VARIANCE_M2.
The JSON record keeps every target.
"""

from __future__ import annotations

import math
import struct
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache

from spiel_edge.messages import cdr, ros2_types
from spiel_edge.messages.ros2_limits import FIELD_OF_VIEW_RAD, SensorLimits  # noqa: F401
from spiel_edge.profile.frame_section import DEFAULT_FRAME_ID

POINT_STAMPED = "geometry_msgs/msg/PointStamped"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
RADAR_TRACKS = "radar_msgs/msg/RadarTracks"
RANGE = "sensor_msgs/msg/Range"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"

# relative topic (under the prefix) or absolute -> type
TOPICS = {
    "point": POINT_STAMPED,
    "targets": POINT_CLOUD2,
    "tracks": RADAR_TRACKS,
    "range": RANGE,
    "/diagnostics": DIAGNOSTIC_ARRAY,
    "/tf_static": TF_MESSAGE,
}
LATCHED = ("/tf_static",)  # transient-local, keep last 1

OPTICAL_SUFFIX = "_optical"
# frame_id -> frame_id_optical: z_optical = x, x_optical = -y, y_optical = -z (REP 103)
OPTICAL_ROTATION_XYZW = (-0.5, 0.5, -0.5, 0.5)

MIN_SCORE = -20.0  # score = -(association cost): below this a target is not published
MAX_VARIANCE_M2 = 1.0  # (1 m)^2, twice the listening range: a wider target says nothing
RANGE_MARGIN_M = 0.025  # about the localisation error: targets this far past the limits pass
DIAGNOSTICS_PERIOD_S = 1.0


@dataclass(frozen=True)
class TargetFilter:
    limits: SensorLimits = field(default_factory=SensorLimits)
    min_score: float = MIN_SCORE
    max_variance_m2: float = MAX_VARIANCE_M2

    def __post_init__(self) -> None:
        lim = self.limits
        object.__setattr__(self, "_r_min", (lim.min_range_m - RANGE_MARGIN_M) * 1e3)
        object.__setattr__(self, "_r_max", (lim.max_range_m + RANGE_MARGIN_M) * 1e3)
        object.__setattr__(self, "_cos", math.cos(lim.field_of_view_rad / 2))
        object.__setattr__(self, "_var_max", self.max_variance_m2 * 1e6)

    def keep(self, target: dict) -> bool:
        """Whether ``target`` (a record's, mm) is published; NaN anywhere fails."""
        try:
            x, y, z = target["position_mm"]
            score = target.get("score")
            if score is not None and not score >= self.min_score:
                return False
            r = math.sqrt(x * x + y * y + z * z)
            if not self._r_min <= r <= self._r_max:
                return False
            bx, by, bz = self.limits.boresight
            if not x * bx + y * by + z * bz > r * self._cos:
                return False
            cov = target.get("covariance_mm2")
            if cov is not None:
                vmax = self._var_max
                if not (
                    0.0 <= cov[0][0] <= vmax
                    and 0.0 <= cov[1][1] <= vmax
                    and 0.0 <= cov[2][2] <= vmax
                ):
                    return False
        except (KeyError, TypeError, ValueError, IndexError):
            return False
        return True


def optical_frame(frame_id: str) -> str:
    return frame_id if frame_id.endswith(OPTICAL_SUFFIX) else frame_id + OPTICAL_SUFFIX


def sensor_transforms(
    frame_id: str, mount: tuple = (), optical: bool = True
) -> list[cdr.StaticTransform]:
    """The mount transforms (parent -> frame_id) and frame_id -> its optical frame."""
    out = list(mount)
    if optical and not frame_id.endswith(OPTICAL_SUFFIX):
        out.append(
            cdr.StaticTransform(
                frame_id, optical_frame(frame_id), (0.0, 0.0, 0.0), OPTICAL_ROTATION_XYZW
            )
        )
    return out


# --- encoders ------------------------------------------------------------------------------

_VEC6F = struct.Struct("<6f")
# position, velocity, acceleration, size; classification; position and velocity covariances
_TRACK = struct.Struct("<12dH2x12f")
_ZEROS6 = (0.0,) * 6  # acceleration and size: not estimated
_NAN12 = _VEC6F.pack(*([math.nan] * 6)) * 2  # their covariances


@cache
def track_uuid(track_id: int) -> bytes:
    """A stable 16-byte id per track id (UUID version 5 of the id in our namespace)."""
    return uuid.uuid5(_UUID_NAMESPACE, str(int(track_id))).bytes


_UUID_NAMESPACE = uuid.UUID("6f1c1d9e-3c59-5d0e-9c1f-5b0e5a2f7a10")


class MessageEncoder:
    """The CDR of each message type for one frame id (the fixed parts packed once)."""

    def __init__(self, frame_id: str):
        self.frame_id = frame_id
        self.cdr = cdr.Ros2Encoder(frame_id)
        raw = frame_id.encode("utf-8") + b"\x00"
        head_pad = -(12 + len(raw)) % 4
        self._head4 = struct.Struct(f"<4siII{len(raw)}s{head_pad}x")  # header, 4-aligned end
        self._head_size = 12 + len(raw) + head_pad  # from the start of the body
        # Range: header, radiation_type (uint8) right after it, float32s 4-aligned
        range_pad = -(13 + len(raw)) % 4
        self._range = struct.Struct(f"<4siII{len(raw)}sB{range_pad}x5f")
        self._raw = raw

    def _header(self, stamp_s) -> bytes:
        sec, nanosec = cdr.stamp_of(stamp_s)
        return self._head4.pack(cdr.ENCAPSULATION, sec, nanosec, len(self._raw), self._raw)

    def range(self, value_m: float, variance_m2: float, limits: SensorLimits, stamp_s) -> bytes:
        sec, nanosec = cdr.stamp_of(stamp_s)
        return self._range.pack(
            cdr.ENCAPSULATION,
            sec,
            nanosec,
            len(self._raw),
            self._raw,
            0,  # ULTRASOUND
            limits.field_of_view_rad,
            limits.min_range_m,
            limits.max_range_m,
            value_m,
            variance_m2,
        )

    def tracks(self, tracks: list[dict], stamp_s) -> bytes:
        parts = [self._header(stamp_s), struct.pack("<I", len(tracks))]
        pos = self._head_size + 4  # offset in the body
        for track in tracks:
            pos += 16  # the uuid, 1-aligned
            pad = -pos % 8
            x, y, z = track["position_mm"]
            vx, vy, vz = track.get("velocity_mm_s") or (0.0, 0.0, 0.0)
            parts.append(track_uuid(track["track_id"]) + b"\x00" * pad)
            parts.append(
                _TRACK.pack(
                    x / 1e3, y / 1e3, z / 1e3, vx / 1e3, vy / 1e3, vz / 1e3, *_ZEROS6,
                    0,  # NO_CLASSIFICATION
                    *_upper6(track.get("covariance_mm2")),
                    *_upper6(track.get("velocity_covariance_mm2_s2")),
                )
            )  # fmt: skip
            parts.append(_NAN12)  # acceleration and size: not estimated
            pos += pad + _TRACK.size + 48
        return b"".join(parts)

    def diagnostics(self, status: dict, stamp_s) -> bytes:
        w = cdr._Writer()
        w.header(*cdr.stamp_of(stamp_s), self.frame_id)
        w.put("I", 1)
        w.put("B", int(status.get("level", 0)))
        w.string(str(status.get("name", "spiel-edge")))
        w.string(str(status.get("message", "")))
        w.string(str(status.get("hardware_id", "")))
        values = status.get("values") or {}
        w.put("I", len(values))
        for key, value in values.items():
            w.string(str(key))
            w.string(str(value))
        return cdr.ENCAPSULATION + bytes(w.buf)


_NAN_TUPLE6 = (math.nan,) * 6


def _upper6(cov) -> tuple:
    """The upper triangle xx xy xz yy yz zz of a 3x3 in mm^2, as m^2 (NaN when missing)."""
    if cov is None:
        return _NAN_TUPLE6
    try:
        a, b = cov[0], cov[1]
        return (a[0] / 1e6, a[1] / 1e6, a[2] / 1e6, b[1] / 1e6, b[2] / 1e6, cov[2][2] / 1e6)
    except (TypeError, IndexError):
        return _NAN_TUPLE6


StatusProvider = Callable[[], dict]


class Ros2Messages:
    """The messages of each record for one sensor: ``of_record(record)`` -> [(topic, bytes)],
    topics as in TOPICS (relative or absolute); the transforms once via ``tf_message()``."""

    def __init__(self, ros2=None, *, status_provider: StatusProvider | None = None):
        """``ros2``: an outputs.ros2.Ros2Settings (frame id, mount, limits); None: defaults."""
        frame_id = getattr(ros2, "frame_id", DEFAULT_FRAME_ID)
        self.settings = ros2
        self.optical = getattr(ros2, "optical", True)  # False: a robot frame (fused records)
        self.frame_id = optical_frame(frame_id) if self.optical else frame_id
        self.encoder = MessageEncoder(self.frame_id)
        self.transforms = sensor_transforms(
            frame_id, getattr(ros2, "transforms", ()), optical=self.optical
        )
        self.filter = TargetFilter(getattr(ros2, "limits", None) or SensorLimits())
        self.status_provider = status_provider
        self._next_diagnostics = -math.inf
        self.counts = {"records": 0, "published_targets": 0, "dropped_targets": 0}

    def of_record(self, record: dict) -> list[tuple[str, bytes]]:
        stamp = record.get("stamp_host") or record.get("host_time")  # synced board time first
        enc = self.encoder
        self.counts["records"] += 1
        keep = self.filter.keep
        all_targets = record.get("targets")
        if all_targets is None and record.get("position_mm") is not None:
            all_targets = [{"position_mm": record["position_mm"]}]
        targets = [t for t in all_targets or () if keep(t)]
        self.counts["published_targets"] += len(targets)
        self.counts["dropped_targets"] += len(all_targets or ()) - len(targets)
        out = []
        if targets:
            out.append(("point", enc.cdr.point_stamped(targets[0]["position_mm"], stamp)))
        out.append(("targets", enc.cdr.targets_cloud(targets, stamp)))
        tracks = record.get("tracks")
        if tracks is not None:
            out.append(("tracks", enc.tracks(tracks, stamp)))
        if self.optical:  # sensor_msgs/Range: one sensor's cone, not a robot's scene
            out.append(("range", self._range(targets, stamp, record)))
        diagnostics = self.diagnostics_due(stamp)
        if diagnostics is not None:
            out.append(("/diagnostics", diagnostics))
        return out

    def _range(self, targets: list[dict], stamp, record: dict | None = None) -> bytes:
        limits = self.filter.limits
        measured = (record or {}).get("range_mm")  # one or two transducers: their own range
        if measured is not None:
            return self._measured_range(measured, record.get("range_var_mm2"), stamp)
        nearest, best = None, math.inf
        for t in targets:
            x, y, z = t["position_mm"]
            r2 = x * x + y * y + z * z
            if r2 < best:
                nearest, best = t, r2
        if nearest is None:
            return self.encoder.range(math.inf, math.nan, limits, stamp)
        r = math.sqrt(best)
        variance = math.nan
        cov = nearest.get("covariance_mm2")
        if cov is not None and r > 0:
            x, y, z = nearest["position_mm"]
            a, b, c = cov
            variance = (
                x * x * a[0] + y * y * b[1] + z * z * c[2]
                + 2.0 * (x * y * a[1] + x * z * a[2] + y * z * b[2])
            ) / (best * 1e6)  # fmt: skip
        return self.encoder.range(r / 1e3, variance, limits, stamp)

    def _measured_range(self, range_mm, var_mm2, stamp) -> bytes:
        """A ranging board's range and variance; +inf outside the limits (REP 117)."""
        limits = self.filter.limits
        r = float(range_mm) / 1e3
        if not limits.min_range_m - RANGE_MARGIN_M <= r <= limits.max_range_m + RANGE_MARGIN_M:
            return self.encoder.range(math.inf, math.nan, limits, stamp)
        variance = math.nan if var_mm2 is None else float(var_mm2) / 1e6
        return self.encoder.range(r, variance, limits, stamp)

    def diagnostics_due(self, stamp) -> bytes | None:
        now = stamp if isinstance(stamp, (int, float)) and stamp > 0 else time.monotonic()
        if now < self._next_diagnostics:
            return None
        self._next_diagnostics = now + DIAGNOSTICS_PERIOD_S
        return self.encoder.diagnostics(self.status(), stamp)

    def status(self) -> dict:
        status = dict(self.status_provider()) if self.status_provider is not None else {}
        status.setdefault("name", "spiel-edge")
        status.setdefault("level", 0)
        values = dict(status.get("values") or {})
        for key, value in self.counts.items():
            values.setdefault(key, value)
        status["values"] = values
        return status

    def tf_message(self, stamp_s: float | None = None) -> bytes:
        return self.encoder.cdr.tf_message(
            self.transforms, time.time() if stamp_s is None else stamp_s
        )


def definitions() -> dict[str, str]:
    """type -> rosbag2 definition for every type the ROS 2 outputs write."""
    return {t: ros2_types.rosbag2_definition(t) for t in set(TOPICS.values())}
