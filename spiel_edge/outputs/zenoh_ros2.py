"""ROS 2 messages over Zenoh for zenoh-bridge-ros2dds (``--zenoh KEY --zenoh-encoding cdr``).

The messages of messages/ros2_messages.py (CDR with its encapsulation header, as a DDS writer
sends it) on the plain keys the bridge maps to ROS 2 topics (the topic without its leading
slash): ``KEY/point``, ``KEY/targets``, ``KEY/tracks``, ``KEY/range``, ``diagnostics`` and
``tf_static``. Each publisher is announced with the bridge's own liveliness token
(``@/<zid>/@ros2_lv/MP/<key>/<type>/<qos>``, wire.bridge_publisher_token), so a bridge creates
the DDS writer as soon as it sees it, not only once a typed ROS reader appears.

``tf_static`` is transient-local: an advanced publisher with a one-sample cache and publisher
detection (what bridges since their switch to Zenoh's advanced subscribers query), and a
queryable on ``@ros2_pub_cache/<zid>/tf_static`` answering the transform (what bridges 1.0 to
1.4 query). It is put once, not re-sent.

docs/ros2.md shows how to see them with ``ros2 topic echo`` through the bridge.
"""

from __future__ import annotations

import logging
from typing import Any

from spiel_edge.messages import ros2_messages as rm
from spiel_edge.messages import ros2_types
from spiel_edge.outputs.rmw_zenoh import wire
from spiel_edge.outputs.sink import STATUS, Sink
from spiel_edge.outputs.zenoh import import_zenoh, open_publishers

log = logging.getLogger(__name__)

PUB_CACHE_PREFIX = "@ros2_pub_cache"  # zenoh-bridge-ros2dds's publication caches (<= 1.4)


class ZenohRos2Sink(Sink):
    """Publish the ROS 2 messages of each record under the key prefix ``key_expr``."""

    capabilities = frozenset({STATUS})  # /diagnostics

    def __init__(
        self,
        key_expr: str,
        ros2: Any = None,
        config: Any = None,
        *,
        settings: Any = None,
    ):
        from spiel_edge.outputs.rmw_zenoh.sink import topics_of

        zenoh = import_zenoh()
        topics_of(key_expr)  # the bridge makes ROS 2 topics of the keys: ROS's rules apply
        self.messages = rm.Ros2Messages(ros2)
        prefix = key_expr.strip("/")
        self.keys = {
            name: name.lstrip("/") if name.startswith("/") else f"{prefix}/{name}"
            for name in rm.TOPICS
        }
        plain = {k: v for k, v in self.keys.items() if k not in rm.LATCHED}
        self._session, self._publishers = open_publishers(
            plain, "APPLICATION_CDR", config, settings
        )
        self.failed = 0
        self._declared: list[Any] = []
        try:
            zid = str(self._session.zid())
            for name, key in self.keys.items():
                qos = wire.LATCHED_QOS if name in rm.LATCHED else wire.SENSOR_QOS
                type_name = rm.TOPICS[name]
                token = wire.bridge_publisher_token(
                    zid, key, type_name, qos, ros2_types.type_hash(type_name)
                )
                self._declared.append(self._session.liveliness().declare_token(token))
            for name in rm.LATCHED:
                self._publishers[name] = zenoh.ext.declare_advanced_publisher(
                    self._session,
                    self.keys[name],
                    encoding=zenoh.Encoding.APPLICATION_CDR,
                    cache=zenoh.ext.CacheConfig(max_samples=1),
                    publisher_detection=True,
                    # sequence numbers, not timestamps, order the cache (as rmw_zenoh's)
                    sample_miss_detection=zenoh.ext.MissDetectionConfig(
                        heartbeat=None, sporadic_heartbeat=0.5
                    ),
                )
            self._queryable = self._declare_tf_cache(zid)
        except Exception:
            self._session.close()
            raise
        self._tf = self.messages.tf_message()
        self._put("/tf_static", self._tf)
        log.info("publishing ROS 2 CDR on Zenoh keys %s", ", ".join(self.keys.values()))

    def set_status_provider(self, provider) -> None:
        self.messages.status_provider = provider

    def _put(self, name: str, payload: bytes) -> None:
        try:
            self._publishers[name].put(payload)
        except Exception as exc:  # zenoh.ZError: keep the run going, like UDP
            self.failed += 1
            if self.failed == 1 or self.failed % 1000 == 0:
                log.warning(
                    "Zenoh put on %s failed (%d so far): %s", self.keys[name], self.failed, exc
                )

    def _declare_tf_cache(self, zid: str):
        """A queryable holding /tf_static, as the bridge's publication caches do."""
        import zenoh

        key = f"{PUB_CACHE_PREFIX}/{zid}/tf_static"

        def answer(query) -> None:
            query.reply(key, self._tf, encoding=zenoh.Encoding.APPLICATION_CDR)

        self.keys["tf_static_cache"] = key
        return self._session.declare_queryable(key, answer)

    def write(self, record: dict) -> None:
        for name, payload in self.messages.of_record(record):
            self._put(name, payload)

    _closed = False

    def close(self) -> None:
        """Undeclare and close the session; safe to call again."""
        if self._closed:
            return
        self._closed = True
        try:
            self._queryable.undeclare()
            for entity in [*self._declared, *self._publishers.values()]:
                try:
                    entity.undeclare()
                except Exception as exc:
                    log.debug("undeclare: %s", exc)
        finally:
            self._session.close()
