"""rmw_zenoh's wire format, as pure functions (no Zenoh here): key expressions, liveliness
tokens, the QoS string, the sample attachment and the entity gid; plus the names ROS accepts.

Read from rmw_zenoh's design document (docs/design.md) and source (liveliness_utils.cpp,
attachment_helpers.cpp, qos.cpp, rmw_publisher_data.cpp) of the Jazzy, Kilted and Rolling
branches, which share this format since rmw_zenoh moved to Zenoh 1.x (binary releases from
Jazzy's 0.2 on):

* data key: ``<domain>/<topic without leading slash>/<pkg::msg::dds_::Type_>/<RIHS01_...>``;
* node token: ``@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>``,
  publisher token: ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP/<enclave>/<namespace>/
  <node>/<topic>/<dds type>/<type hash>/<qos>``, each name with ``/`` replaced by ``%``
  (``%`` alone for the root namespace and no enclave);
* QoS: ``rel:dur:hist,depth:dl_s,dl_ns:ls_s,ls_ns:liv,lease_s,lease_ns``, each value left
  empty when it is rmw_zenoh's default (reliable, volatile, keep last, depth 42, infinite
  durations, automatic liveliness), else the rmw enum's number;
* attachment (Zenoh's serializer): int64 sequence number (from 1), int64 source timestamp
  (ns since the Unix epoch), the gid as a sequence of 16 bytes (length 16 as one LEB128 byte),
  all little-endian: 33 bytes;
* gid: XXH3-128 of the entity's liveliness key expression, low 64 bits then high 64 bits,
  little-endian.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

from spiel_edge.errors import ConfigError

ADMIN_SPACE = "@ros2_lv"
# ROS 2 distributions and the type-hash part of their keys and tokens: Humble's rmw_zenoh
# (0.1.x) has no type hashes (REP 2011 came with Iron) and writes this word in their place;
# Jazzy (0.2.x), Kilted (0.6.x), Lyrical (0.10.x) and Rolling (0.12.x) write RIHS01_<sha256>.
ROS_DISTROS = ("humble", "jazzy", "kilted", "lyrical", "rolling")
DEFAULT_DISTRO = "jazzy"
NO_TYPE_HASH = "TypeHashNotSupported"
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"
GID_SIZE = 16
MAX_DOMAIN_ID = 232  # DDS's port mapping ends here; the bridge's DDS side needs it too
MAX_TOPIC_LENGTH = 255 - 8  # rmw's limit on a fully qualified topic name (DDS prefix room)

# rmw enums (rmw/types.h)
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
AUTOMATIC = 1
INFINITE_S, INFINITE_NS = 9223372036, 854775807  # RMW_DURATION_INFINITE


@dataclass(frozen=True)
class Qos:
    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10


# rmw_zenoh's defaults: a value equal to these is left empty in the token
_DEFAULT = Qos(RELIABLE, VOLATILE, KEEP_LAST, 42)
SENSOR_QOS = Qos(depth=10)  # reliable, volatile, keep last 10 (rclcpp's default profile)
LATCHED_QOS = Qos(durability=TRANSIENT_LOCAL, depth=1)  # tf2's static broadcaster


def qos_to_keyexpr(qos: Qos) -> str:
    """The QoS part of a liveliness token (``qos_to_keyexpr`` in liveliness_utils.cpp)."""

    def value(v: int, default: int) -> str:
        return "" if v == default else str(v)

    return (
        f"{value(qos.reliability, _DEFAULT.reliability)}:"
        f"{value(qos.durability, _DEFAULT.durability)}:"
        f"{value(qos.history, _DEFAULT.history)},{value(qos.depth, _DEFAULT.depth)}"
        ":,:,:,,"  # deadline, lifespan, liveliness and its lease: the defaults
    )


def keyexpr_to_qos(text: str) -> Qos:
    """Inverse of :func:`qos_to_keyexpr` for the four values spiel-edge sets (ValueError)."""
    parts = text.split(":")
    if len(parts) != 6:
        raise ValueError(f"QoS {text!r}: expected 6 ':'-separated parts")
    history, _sep, depth = parts[2].partition(",")
    if parts[3].count(",") != 1 or parts[4].count(",") != 1 or parts[5].count(",") != 2:
        raise ValueError(f"QoS {text!r}: malformed durations")

    def num(v: str, default: int) -> int:
        return default if v == "" else int(v)

    return Qos(
        num(parts[0], _DEFAULT.reliability),
        num(parts[1], _DEFAULT.durability),
        num(history, _DEFAULT.history),
        num(depth, _DEFAULT.depth),
    )


def mangle(name: str) -> str:
    return name.replace("/", "%")


def demangle(name: str) -> str:
    return name.replace("%", "/")


def distro_type_hash(distro: str, type_hash: str) -> str:
    """The type-hash part ``distro``'s rmw_zenoh writes for a type whose RIHS01 is ``type_hash``."""
    if distro not in ROS_DISTROS:
        raise ConfigError(f"ROS 2 distribution {distro!r}: one of {', '.join(ROS_DISTROS)}")
    return NO_TYPE_HASH if distro == "humble" else type_hash


def topic_key(domain_id: int, topic: str, dds_type: str, type_hash: str) -> str:
    return f"{domain_id}/{topic.strip('/')}/{dds_type}/{type_hash}"


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node: str) -> str:
    ns = mangle(namespace) if namespace else "%"
    return f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{node_id}/{NODE}/%/{ns}/{mangle(node)}"


def publisher_token(
    domain_id: int,
    zid: str,
    node_id: int,
    entity_id: int,
    namespace: str,
    node: str,
    topic: str,
    dds_type: str,
    type_hash: str,
    qos: Qos,
) -> str:
    ns = mangle(namespace) if namespace else "%"
    return (
        f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{entity_id}/{PUBLISHER}/%/{ns}/"
        f"{mangle(node)}/{mangle(topic)}/{dds_type}/{type_hash}/{qos_to_keyexpr(qos)}"
    )


@dataclass(frozen=True)
class Token:
    """A parsed liveliness token (what a receiving graph cache learns)."""

    domain_id: int
    zid: str
    node_id: str
    entity_id: str
    kind: str
    enclave: str
    namespace: str
    node: str
    topic: str | None = None
    dds_type: str | None = None
    type_hash: str | None = None
    qos: Qos | None = None


def parse_token(key: str) -> Token:
    """A liveliness key expression -> Token (ValueError when it is not rmw_zenoh's)."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or any(not p for p in parts):
        raise ValueError(f"not an rmw_zenoh liveliness token: {key!r}")
    kind = parts[5]
    head = (int(parts[1]), parts[2], parts[3], parts[4], kind)
    names = tuple(demangle(p) for p in parts[6:9])
    if kind == NODE:
        if len(parts) != 9:
            raise ValueError(f"node token with {len(parts)} parts: {key!r}")
        return Token(*head, *names)
    if kind not in (PUBLISHER, SUBSCRIPTION, "SS", "SC") or len(parts) != 13:
        raise ValueError(f"entity token with {len(parts)} parts or kind {kind!r}: {key!r}")
    return Token(
        *head, *names, demangle(parts[9]), demangle(parts[10]), parts[11], keyexpr_to_qos(parts[12])
    )


def parse_topic_key(key: str) -> tuple[int, str, str, str]:
    """(domain id, topic with its leading slash, dds type, type hash) of a data key."""
    parts = key.split("/")
    hashed = parts[-1].startswith("RIHS01_") or parts[-1] == NO_TYPE_HASH
    if len(parts) < 4 or not parts[0].isdigit() or not hashed:
        raise ValueError(f"not an rmw_zenoh topic key: {key!r}")
    return int(parts[0]), "/" + "/".join(parts[1:-2]), parts[-2], parts[-1]


_ATTACHMENT = struct.Struct("<qqB16s")


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The 33 bytes rmw_zenoh attaches to every sample."""
    return _ATTACHMENT.pack(sequence_number, source_timestamp_ns, GID_SIZE, gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, gid); ValueError when malformed."""
    if len(data) != _ATTACHMENT.size:
        raise ValueError(f"attachment of {len(data)} bytes, expected {_ATTACHMENT.size}")
    seq, stamp, size, gid = _ATTACHMENT.unpack(data)
    if size != GID_SIZE:
        raise ValueError(f"attachment gid length {size}, expected {GID_SIZE}")
    return seq, stamp, gid


def gid_of(token: str) -> bytes:
    """The entity gid rmw_zenoh derives from its liveliness key expression."""
    import xxhash  # the 'zenoh' extra

    digest = xxhash.xxh3_128_intdigest(token.encode("utf-8"))
    return struct.pack("<QQ", digest & (2**64 - 1), digest >> 64)


# --- names ROS accepts (rmw_validate_full_topic_name, rmw_validate_node_name) -----------------

_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def topic_name_problem(name: str) -> str | None:
    """Why ``name`` is not a fully qualified ROS 2 topic name (None when it is)."""
    if not name.startswith("/"):
        return "must start with '/'"
    if len(name) > MAX_TOPIC_LENGTH:
        return f"is longer than {MAX_TOPIC_LENGTH} characters"
    if name != "/" and name.endswith("/"):
        return "must not end with '/'"
    for token in name[1:].split("/"):
        if not token:
            return "must not contain '//'"
        if not _TOKEN.fullmatch(token):
            return (
                f"has the part {token!r}: only letters, digits and '_', not starting with a digit"
            )
    return None


def check_topic(name: str, option: str) -> str:
    problem = topic_name_problem(name)
    if problem:
        raise ConfigError(f"{option}: the ROS 2 topic {name!r} {problem}")
    return name


def check_domain_id(value: object, option: str = "--ros-domain-id") -> int:
    try:
        domain = int(str(value).strip())
    except ValueError:
        domain = -1
    if not 0 <= domain <= MAX_DOMAIN_ID:
        raise ConfigError(
            f"{option} {value!r}: a ROS domain id is a whole number 0-{MAX_DOMAIN_ID}"
        )
    return domain


# --- zenoh-bridge-ros2dds's announcement of a publisher (liveliness_mgt.rs) -----------------


def bridge_publisher_token(zid: str, key: str, type_name: str, qos: Qos, type_hash: str) -> str:
    """``@/<zid>/@ros2_lv/MP/<key>/<type>/<qos>`` with ``/`` escaped as ``§``; the QoS in the
    bridge's DDS form (keyless, reliability, durability, history,depth, user data with the type
    hash as ROS 2 Iron and later put there)."""
    reliability = "1" if qos.reliability == RELIABLE else "0"  # DDS: BEST_EFFORT 0, RELIABLE 1
    durability = "1" if qos.durability == TRANSIENT_LOCAL else "0"  # VOLATILE 0, TRANSIENT_LOCAL 1
    history = f"0,{qos.depth}" if qos.history == KEEP_LAST else f"1,{qos.depth}"
    qos_ke = f":{reliability}:{durability}:{history}:typehash={type_hash};"
    escape = "§"
    return (
        f"@/{zid}/@ros2_lv/MP/{key.replace('/', escape)}/{type_name.replace('/', escape)}/{qos_ke}"
    )
