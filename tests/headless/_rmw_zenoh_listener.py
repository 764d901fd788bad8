"""A test-only ROS 2 subscriber that receives as rmw_zenoh does, written from rmw_zenoh's design
document (docs/design.md: "Topic and Service name mapping", "Graph Cache", "Publishers",
"Quality of Service"), independent of spiel_edge's own wire module:

* graph: liveliness tokens under ``@ros2_lv/<domain>/**`` (a liveliness query for those that
  exist, a liveliness subscriber for new ones), split on ``/``, names demangled (``%`` ->
  ``/``), the QoS string parsed into reliability, durability, history and depth;
* data: a subscriber on ``<domain>/**``; the key must be ``<domain>/<topic>/<dds type>/
  <type hash>`` of a publisher in the graph, the type hash must be the one computed
  independently (rosbags' hash_rihs01), the attachment must decode (int64 sequence number,
  int64 source timestamp, a 16-byte gid with its length) with the gid of the announcing
  token, and the payload must deserialize (rosbags);
* transient-local topics through an advanced subscriber asking for history of late publishers.
"""

from __future__ import annotations

import struct
import threading
import time
from dataclasses import dataclass, field

import xxhash
import zenoh
import zenoh.ext
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.msg import get_types_from_msg

EXTRA_TYPES = {  # types rosbags has no store for: the upstream definitions
    "unique_identifier_msgs/msg/UUID": "uint8[16] uuid",
    "radar_msgs/msg/RadarTrack": "uint16 NO_CLASSIFICATION=0\nuint16 STATIC=1\nuint16 DYNAMIC=2\n"
    "unique_identifier_msgs/UUID uuid\ngeometry_msgs/Point position\ngeometry_msgs/Vector3 "
    "velocity\ngeometry_msgs/Vector3 acceleration\ngeometry_msgs/Vector3 size\nuint16 "
    "classification\nfloat32[6] position_covariance\nfloat32[6] velocity_covariance\n"
    "float32[6] acceleration_covariance\nfloat32[6] size_covariance",
    "radar_msgs/msg/RadarTracks": "std_msgs/Header header\nradar_msgs/RadarTrack[] tracks",
}


def typestore(store=Stores.ROS2_JAZZY):
    ts = get_typestore(store)
    types = {}
    for name, text in EXTRA_TYPES.items():
        if name not in ts.fielddefs:
            types.update(get_types_from_msg(text, name))
    ts.register(types)
    return ts


def dds_name(ros_type: str) -> str:
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def ros_type(dds: str) -> str:
    package, kind, _dds, name = dds.split("::")
    return f"{package}/{kind}/{name[:-1]}"


@dataclass
class Endpoint:
    kind: str
    zid: str
    node: str
    namespace: str
    topic: str = ""
    type_name: str = ""
    type_hash: str = ""
    reliability: int = 0
    durability: int = 0
    history: int = 0
    depth: int = 0
    gid: bytes = b""


def parse_qos(text: str) -> tuple[int, int, int, int]:
    """rmw_zenoh's defaults for empty fields: reliable 1, volatile 2, keep last 1, depth 42."""
    rel, dur, hist, *_rest = text.split(":")
    history, depth = hist.split(",")
    return int(rel or 1), int(dur or 2), int(history or 1), int(depth or 42)


def parse_token(key: str) -> Endpoint:
    parts = key.split("/")
    assert parts[0] == "@ros2_lv" and all(parts), key
    kind = parts[5]
    ns, node = parts[7].replace("%", "/"), parts[8].replace("%", "/")
    if kind == "NN":
        assert len(parts) == 9 and parts[3] == parts[4], key
        return Endpoint(kind, parts[2], node, ns)
    assert len(parts) == 13, key
    rel, dur, hist, depth = parse_qos(parts[12])
    digest = xxhash.xxh3_128_intdigest(key.encode())
    gid = struct.pack("<QQ", digest & (2**64 - 1), digest >> 64)
    return Endpoint(
        kind, parts[2], node, ns, parts[9].replace("%", "/"), parts[10], parts[11],
        rel, dur, hist, depth, gid,
    )  # fmt: skip


@dataclass
class Received:
    topic: str
    type_name: str
    message: object
    seq: int
    stamp_ns: int
    gid: bytes
    at: float


@dataclass
class Listener:
    """Graph and samples of one ROS domain, as an rmw_zenoh subscriber would see them."""

    session: zenoh.Session
    domain: int = 0
    store: object = field(default_factory=typestore)
    endpoints: dict = field(default_factory=dict)  # token key -> Endpoint
    samples: list = field(default_factory=list)
    problems: list = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    humble: bool = False  # Humble's rmw_zenoh (0.1.x): TypeHashNotSupported for every type

    def expected_hash(self, type_name: str) -> str:
        return "TypeHashNotSupported" if self.humble else self.store.hash_rihs01(type_name)

    def start(self) -> Listener:
        space = f"@ros2_lv/{self.domain}/**"
        self._lv = self.session.liveliness().declare_subscriber(space, self._on_token)
        for reply in self.session.liveliness().get(space, timeout=2.0):
            if reply.ok is not None:
                self._add_token(str(reply.ok.key_expr))
        self._sub = self.session.declare_subscriber(f"{self.domain}/**", self._on_sample)
        return self

    def _on_token(self, sample) -> None:
        key = str(sample.key_expr)
        if sample.kind == zenoh.SampleKind.DELETE:
            with self.lock:
                self.endpoints.pop(key, None)
        else:
            self._add_token(key)

    def _add_token(self, key: str) -> None:
        try:
            endpoint = parse_token(key)
        except (AssertionError, ValueError) as exc:
            self.problems.append(f"bad token {key}: {exc}")
            return
        with self.lock:
            self.endpoints[key] = endpoint

    def publishers(self) -> dict[str, Endpoint]:
        with self.lock:
            return {e.topic: e for e in self.endpoints.values() if e.kind == "MP"}

    def nodes(self) -> list[Endpoint]:
        with self.lock:
            return [e for e in self.endpoints.values() if e.kind == "NN"]

    def subscribe_latched(self, key: str):
        """An advanced subscriber with history, as rmw_zenoh declares for TRANSIENT_LOCAL."""
        return zenoh.ext.declare_advanced_subscriber(
            self.session,
            key,
            self._on_sample,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
            recovery=zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
            subscriber_detection=True,
        )

    def _on_sample(self, sample) -> None:
        at = time.monotonic()
        key = str(sample.key_expr)
        try:
            parts = key.split("/")
            assert int(parts[0]) == self.domain, key
            topic = "/" + "/".join(parts[1:-2])
            type_name, type_hash = ros_type(parts[-2]), parts[-1]
            assert type_hash == self.expected_hash(type_name), f"type hash of {key}"
            raw = sample.attachment.to_bytes() if sample.attachment is not None else b""
            assert len(raw) == 33 and raw[16] == 16, f"attachment {raw.hex()}"
            seq, stamp = struct.unpack_from("<qq", raw)
            gid = raw[17:]
            message = self.store.deserialize_cdr(sample.payload.to_bytes(), type_name)
        except Exception as exc:  # noqa: BLE001 - a test records every problem
            self.problems.append(f"{key}: {exc!r}")
            return
        with self.lock:
            self.samples.append(Received(topic, type_name, message, seq, stamp, gid, at))

    def received(self, topic: str) -> list[Received]:
        with self.lock:
            return [s for s in self.samples if s.topic == topic]
