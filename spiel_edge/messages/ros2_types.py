"""The ROS 2 message types spiel-edge writes: their .msg definitions, the rosbag2 form of them
(``ros2msg`` schemas in MCAP) and their RIHS01 type hashes (REP 2016), without rosidl.

A type hash is the SHA-256 of the type description in JSON: the type's fields (name, type id,
array capacity, string capacity, nested type name; no constants, no default values) and the
descriptions of every type it refers to, sorted by name. rmw_zenoh puts the hash in every key
expression and liveliness token; rosbag2 (Jazzy and later) stores it per topic. The hashes of
the standard types here are the same in Iron, Jazzy, Kilted and Rolling (tests check them
against ``rosbags``' own computation for each distribution's definitions).

``spiel_msgs`` types have no standard equivalent; their package for colcon is
``packaging/ros2/spiel_msgs`` (tests check that its .msg files are these definitions).
"""

from __future__ import annotations

import hashlib
import json
import re
from functools import cache

# type -> its .msg text (constants included: they are part of the definition rosbag2 stores,
# not of the hash). Nested types are always written as pkg/Type.
MSG: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "std_msgs/msg/String": "string data",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w",
    "geometry_msgs/msg/PointStamped": "std_msgs/Header header\ngeometry_msgs/Point point",
    "geometry_msgs/msg/Transform": "geometry_msgs/Vector3 translation\n"
    "geometry_msgs/Quaternion rotation",
    "geometry_msgs/msg/TransformStamped": "std_msgs/Header header\nstring child_frame_id\n"
    "geometry_msgs/Transform transform",
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    "sensor_msgs/msg/PointField": "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\n"
    "uint8 INT32=5\nuint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\n"
    "string name\nuint32 offset\nuint8 datatype\nuint32 count",
    "sensor_msgs/msg/PointCloud2": "std_msgs/Header header\nuint32 height\nuint32 width\n"
    "sensor_msgs/PointField[] fields\nbool is_bigendian\nuint32 point_step\nuint32 row_step\n"
    "uint8[] data\nbool is_dense",
    "sensor_msgs/msg/Range": "uint8 ULTRASOUND=0\nuint8 INFRARED=1\nstd_msgs/Header header\n"
    "uint8 radiation_type\nfloat32 field_of_view\nfloat32 min_range\nfloat32 max_range\n"
    "float32 range\nfloat32 variance",
    "unique_identifier_msgs/msg/UUID": "uint8[16] uuid",
    "radar_msgs/msg/RadarTrack": "uint16 NO_CLASSIFICATION=0\nuint16 STATIC=1\nuint16 DYNAMIC=2\n"
    "unique_identifier_msgs/UUID uuid\ngeometry_msgs/Point position\n"
    "geometry_msgs/Vector3 velocity\ngeometry_msgs/Vector3 acceleration\n"
    "geometry_msgs/Vector3 size\nuint16 classification\nfloat32[6] position_covariance\n"
    "float32[6] velocity_covariance\nfloat32[6] acceleration_covariance\n"
    "float32[6] size_covariance",
    "radar_msgs/msg/RadarTracks": "std_msgs/Header header\nradar_msgs/RadarTrack[] tracks",
    "diagnostic_msgs/msg/KeyValue": "string key\nstring value",
    "diagnostic_msgs/msg/DiagnosticStatus": "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\n"
    "byte level\nstring name\nstring message\nstring hardware_id\n"
    "diagnostic_msgs/KeyValue[] values",
    "diagnostic_msgs/msg/DiagnosticArray": "std_msgs/Header header\n"
    "diagnostic_msgs/DiagnosticStatus[] status",
    # spiel_msgs: packaging/ros2/spiel_msgs/msg/Acquisition.msg
    "spiel_msgs/msg/Acquisition": "std_msgs/Header header\nint64 seq\nint64 device_time_us\n"
    "uint32 channels\nuint32 samples\nfloat64[] frames",
}

SPIEL_MSGS = ("spiel_msgs/msg/Acquisition",)

# REP 2016 / type_description_interfaces FieldType ids
_PRIMITIVE_IDS = {
    "int8": 2,
    "uint8": 3,
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float32": 10,
    "float64": 11,
    "char": 13,
    "wchar": 14,
    "bool": 15,
    "byte": 16,
    "string": 17,
    "wstring": 18,
}
_NESTED = 1
_BOUNDED_STRING = {"string": 21, "wstring": 22}
_ARRAY, _BOUNDED_SEQUENCE, _UNBOUNDED_SEQUENCE = 48, 96, 144
_FIELD = re.compile(
    r"(?P<base>[A-Za-z][A-Za-z0-9_/]*)(?:<=(?P<strcap>\d+))?"
    r"(?P<array>\[(?P<bounded><=)?(?P<size>\d*)\])?"
)


def _full_name(name: str, package: str) -> str:
    """``pkg/Type`` or ``Type`` (same package) -> ``pkg/msg/Type``."""
    parts = name.split("/")
    if len(parts) == 3:
        return name
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return f"{package}/msg/{name}"


def fields(type_name: str) -> list[tuple[str, dict]]:
    """(field name, FieldType dict) of a type in MSG, constants left out."""
    package = type_name.split("/")[0]
    out = []
    for line in MSG[type_name].splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        spec, name = line.split()[:2]
        if "=" in name or "=" in line.split(None, 1)[1].split()[0]:
            continue  # a constant
        m = _FIELD.fullmatch(spec)
        if m is None:
            raise ValueError(f"{type_name}: cannot parse field type {spec!r}")
        base, nested = m["base"], ""
        if base in _PRIMITIVE_IDS:
            type_id = _PRIMITIVE_IDS[base]
            if m["strcap"]:
                type_id = _BOUNDED_STRING[base]
        else:
            type_id, nested = _NESTED, _full_name(base, package)
        capacity = 0
        if m["array"]:
            if m["bounded"]:
                type_id, capacity = type_id + _BOUNDED_SEQUENCE, int(m["size"])
            elif m["size"]:
                type_id, capacity = type_id + _ARRAY, int(m["size"])
            else:
                type_id += _UNBOUNDED_SEQUENCE
        out.append(
            (
                name,
                {
                    "type_id": type_id,
                    "capacity": capacity,
                    "string_capacity": int(m["strcap"] or 0),
                    "nested_type_name": nested,
                },
            )
        )
    if not out:  # an empty message gets a placeholder member, as rosidl does
        out.append(
            (
                "structure_needs_at_least_one_member",
                {"type_id": 3, "capacity": 0, "string_capacity": 0, "nested_type_name": ""},
            )
        )
    return out


def dependencies(type_name: str) -> list[str]:
    """Every type ``type_name`` refers to, directly or not, in first-use order."""
    seen: list[str] = []

    def visit(name: str) -> None:
        for _field, ftype in fields(name):
            nested = ftype["nested_type_name"]
            if nested and nested not in seen:
                seen.append(nested)
                visit(nested)

    visit(type_name)
    return seen


def _description(type_name: str) -> dict:
    return {
        "type_name": type_name,
        "fields": [{"name": name, "type": ftype} for name, ftype in fields(type_name)],
    }


@cache
def type_hash(type_name: str) -> str:
    """``RIHS01_`` + the SHA-256 of the type description (REP 2016)."""
    description = {
        "type_description": _description(type_name),
        "referenced_type_descriptions": [
            _description(name) for name in sorted(dependencies(type_name))
        ],
    }
    text = json.dumps(description, separators=(", ", ": "), ensure_ascii=False)
    return "RIHS01_" + hashlib.sha256(text.encode("utf-8")).hexdigest()


def short_name(type_name: str) -> str:
    """``pkg/msg/Type`` -> ``pkg/Type`` (the form inside rosbag2's concatenated definitions)."""
    package, _msg, name = type_name.split("/")
    return f"{package}/{name}"


@cache
def rosbag2_definition(type_name: str) -> str:
    """The definition as rosbag2 stores it (schema encoding ``ros2msg``): the type's .msg,
    then each type it uses after a line of 80 ``=`` and ``MSG: pkg/Type``."""
    parts = [MSG[type_name]]
    for name in dependencies(type_name):
        parts.append(f"MSG: {short_name(name)}\n{MSG[name]}")
    return ("\n" + "=" * 80 + "\n").join(parts)


def dds_type_name(type_name: str) -> str:
    """``pkg/msg/Type`` -> ``pkg::msg::dds_::Type_`` (the name rmw_zenoh keys carry)."""
    package, kind, name = type_name.split("/")
    return f"{package}::{kind}::dds_::{name}_"
