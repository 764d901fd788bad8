"""A ROS 2 node on Zenoh without ROS: what an rmw_zenoh node (Jazzy, Kilted, Rolling) sees as
node ``/spiel_edge`` publishing ``/KEY/point``, ``/KEY/targets``, ``/KEY/tracks``,
``/KEY/range``, ``/diagnostics`` and ``/tf_static`` (messages/ros2_messages.py).

Per publisher: a Zenoh publisher on the topic's key (wire.topic_key), a liveliness token
announcing it (type, type hash, QoS) and the rmw_zenoh attachment on every sample (sequence
number, source time, gid). ``/tf_static`` is transient-local: Zenoh's advanced publisher with
a cache of one sample and publisher detection, as rmw_zenoh declares it, so a late
subscriber's history query gets the transform at once; the transform is put once.

The session: peer mode (rmw_zenoh's) or client, connecting to ``--zenoh-connect`` endpoints,
by default (no endpoint, no ZENOH_CONFIG) DEFAULT_ROUTER as rmw_zenoh's sessions do. Nothing here blocks the run loop: a router that is
not there is warned about once and the run goes on (a peer session keeps trying by itself; a
client session that cannot open is opened again in the background every RETRY_S, and declares
everything then); samples meanwhile are dropped, /tf_static waits in the cache.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import replace
from typing import Any

from spiel_edge.errors import ConfigError
from spiel_edge.messages import ros2_messages as rm
from spiel_edge.messages import ros2_types
from spiel_edge.outputs.rmw_zenoh import wire
from spiel_edge.outputs.sink import STATUS, Sink
from spiel_edge.outputs.zenoh import import_zenoh, session_config, zenoh_reason

log = logging.getLogger(__name__)

NODE_NAME = "spiel_edge"
DEFAULT_ROUTER = "tcp/localhost:7447"  # rmw_zenoh's default: rmw_zenohd on this host
NODE_ID = 0
RETRY_S = 1.0  # a client session that could not open is tried again this often
WATCH_S = 1.0  # how often the run loop checks that a router or peer is connected
TF_MISS_HEARTBEAT_S = 0.5  # rmw_zenoh's sporadic heartbeat for reliable transient-local


def topics_of(prefix: str) -> dict[str, str]:
    """TOPICS names -> absolute ROS 2 topics under ``/prefix`` (ConfigError when ROS would
    reject one)."""
    base = "/" + prefix.strip("/")
    out = {}
    for name in rm.TOPICS:
        topic = name if name.startswith("/") else f"{base}/{name}"
        out[name] = wire.check_topic(topic, f"--zenoh {prefix!r}")
    return out


class RmwZenohSink(Sink):
    """Publish each record's ROS 2 messages as rmw_zenoh does."""

    capabilities = frozenset({STATUS})  # /diagnostics

    def __init__(
        self,
        prefix: str = "spiel",
        ros2: Any = None,
        settings: Any = None,
        config: Any = None,
        *,
        node_name: str = NODE_NAME,
    ):
        from spiel_edge.outputs.ros2 import ZenohSettings

        self.zenoh = import_zenoh()
        self.settings = settings or ZenohSettings()
        if not self.settings.connect and config is None and not os.environ.get("ZENOH_CONFIG"):
            # rmw_zenoh's own sessions connect to the router on this host
            self.settings = replace(self.settings, connect=(DEFAULT_ROUTER,))
        self.domain_id = wire.check_domain_id(self.settings.domain_id)
        self.topics = topics_of(prefix)
        self.messages = rm.Ros2Messages(ros2)
        self.node_name = node_name
        self._config = session_config(config, self.settings, rmw_zenoh=True)
        self.failed = 0
        self.dropped = 0
        self.tokens: dict[str, str] = {}  # topic -> liveliness key expression
        self.keys: dict[str, str] = {}  # topic -> data key expression
        self._session = None
        self._pubs: dict[str, Any] = {}
        self._gids: dict[str, bytes] = {}
        self._seq: dict[str, int] = {}
        self._declared: list[Any] = []
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self._warned = False
        self._next_watch = 0.0
        self._retry: threading.Thread | None = None
        try:
            self._open()
        except ConfigError:
            raise
        except Exception as exc:  # zenoh.ZError: no router for a client, ...
            self._warn_once(f"cannot open the Zenoh session ({zenoh_reason(exc)})")
            self._retry = threading.Thread(target=self._retry_open, daemon=True, name="rmw-zenoh")
            self._retry.start()

    # --- session ------------------------------------------------------------------------------

    def _open(self) -> None:
        session = self.zenoh.open(self._config)
        try:
            self._declare(session)
        except Exception:
            session.close()
            raise
        with self._lock:
            if self._closing.is_set():  # closed while this (retry) opened it
                session.close()
                return
            self._session = session
        log.info(
            "ROS 2 node /%s on Zenoh (rmw_zenoh format of %s, domain %d): %s",
            self.node_name,
            self.settings.ros_distro,
            self.domain_id,
            ", ".join(self.topics.values()),
        )

    def _retry_open(self) -> None:
        while not self._closing.wait(RETRY_S):
            try:
                self._open()
            except Exception as exc:
                log.debug("Zenoh session still not open: %s", exc)
                continue
            log.warning("Zenoh session open: publishing ROS 2 topics again")
            self._warned = False
            return

    def _declare(self, session) -> None:
        zenoh, ext = self.zenoh, self.zenoh.ext
        zid = str(session.zid())
        node = wire.node_token(self.domain_id, zid, NODE_ID, "/", self.node_name)
        declared = [session.liveliness().declare_token(node)]
        self.tokens["node"] = node
        pubs, gids = {}, {}
        for entity_id, (name, topic) in enumerate(self.topics.items(), start=1):
            type_name = rm.TOPICS[name]
            latched = name in rm.LATCHED
            qos = wire.LATCHED_QOS if latched else wire.SENSOR_QOS
            type_hash = wire.distro_type_hash(
                self.settings.ros_distro, ros2_types.type_hash(type_name)
            )
            dds = ros2_types.dds_type_name(type_name)
            key = wire.topic_key(self.domain_id, topic, dds, type_hash)
            if latched:
                pub = ext.declare_advanced_publisher(
                    session,
                    key,
                    cache=ext.CacheConfig(max_samples=qos.depth),
                    publisher_detection=True,
                    sample_miss_detection=ext.MissDetectionConfig(
                        heartbeat=None, sporadic_heartbeat=TF_MISS_HEARTBEAT_S
                    ),
                    congestion_control=zenoh.CongestionControl.DROP,
                    reliability=zenoh.Reliability.RELIABLE,
                )
            else:
                pub = session.declare_publisher(
                    key,
                    congestion_control=zenoh.CongestionControl.DROP,  # never block the run loop
                    reliability=zenoh.Reliability.RELIABLE,
                )
            token = wire.publisher_token(
                self.domain_id, zid, NODE_ID, entity_id, "/", self.node_name, topic, dds,
                type_hash, qos,
            )  # fmt: skip
            declared += [pub, session.liveliness().declare_token(token)]
            pubs[name], gids[name] = pub, wire.gid_of(token)
            self.tokens[topic], self.keys[topic] = token, key
            self._seq.setdefault(name, 0)
        self._pubs, self._gids, self._declared = pubs, gids, declared
        self._put("/tf_static", self.messages.tf_message())

    def _warn_once(self, problem: str) -> None:
        if not self._warned:
            self._warned = True
            where = ", ".join(self.settings.connect) or "the local network"
            log.warning(
                "Zenoh: %s; no ROS 2 router or peer reachable at %s yet. The run goes on, "
                "ROS 2 messages are dropped until it is, and Zenoh keeps trying",
                problem,
                where,
            )

    def _watch(self) -> None:
        """Every WATCH_S: is anyone there? Warn once when not, say when it is back."""
        now = time.monotonic()
        if now < self._next_watch or self._session is None:
            return
        self._next_watch = now + WATCH_S
        info = self._session.info
        connected = bool(info.routers_zid()) or bool(info.peers_zid())
        if not connected and self.settings.connect:
            self._warn_once("not connected")
        elif connected and self._warned:
            self._warned = False
            log.warning("Zenoh: connected again; ROS 2 messages flow")

    # --- publishing ---------------------------------------------------------------------------

    def set_status_provider(self, provider) -> None:
        self.messages.status_provider = provider

    def _put(self, name: str, payload: bytes) -> None:
        pub = self._pubs.get(name)
        if pub is None:
            self.dropped += 1
            return
        self._seq[name] += 1
        attachment = wire.attachment(self._seq[name], time.time_ns(), self._gids[name])
        try:
            pub.put(payload, attachment=attachment)
        except Exception as exc:  # zenoh.ZError: keep the run going
            self.failed += 1
            if self.failed == 1 or self.failed % 1000 == 0:
                log.warning("Zenoh put on %s failed (%d so far): %s", name, self.failed, exc)

    def write(self, record: dict) -> None:
        messages = self.messages.of_record(record)
        if self._session is None:
            self.dropped += len(messages)
            return
        for name, payload in messages:
            self._put(name, payload)
        self._watch()

    def close(self) -> None:
        self._closing.set()
        with self._lock:
            session, self._session = self._session, None
        if session is None:
            return
        try:
            for entity in reversed(self._declared):
                try:
                    entity.undeclare()
                except Exception as exc:  # already gone with the session
                    log.debug("undeclare: %s", exc)
        finally:
            session.close()
