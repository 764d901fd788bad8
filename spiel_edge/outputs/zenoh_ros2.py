"""ROS 2 messages over Zenoh without rclpy (``--zenoh KEY --zenoh-encoding cdr``).

Each message is the CDR a DDS writer sends (encapsulation header included), on the plain keys
that zenoh-bridge-ros2dds maps to ROS 2 topics (topic name without its leading slash):

* ``KEY/point``: geometry_msgs/msg/PointStamped (the best target, metres) -> ``/KEY/point``;
* ``KEY/targets``: sensor_msgs/msg/PointCloud2 (every target) -> ``/KEY/targets``;
* ``tf_static``: tf2_msgs/msg/TFMessage (the profile's ``[frame]``, ``--parent-frame``,
  ``--static-tf``) -> ``/tf_static``, sent at start and then every TF_PERIOD_S, since a plain
  Zenoh publisher keeps no latched copy for a subscriber that joins later. The last one is also
  answered to queries on ``@ros2_pub_cache/<session id>/tf_static``, where
  zenoh-bridge-ros2dds (1.0 to 1.4) asks for the history of a transient-local topic when a ROS
  reader of it appears (docs/ros2.md: untested against a real bridge).

docs/ros2.md shows how to see them with ``ros2 topic echo`` through the bridge.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from spiel_edge.io.cdr import Ros2Encoder
from spiel_edge.outputs.ros2 import Ros2Settings
from spiel_edge.outputs.zenoh import open_publishers

log = logging.getLogger(__name__)

TF_PERIOD_S = 1.0
PUB_CACHE_PREFIX = "@ros2_pub_cache"  # zenoh-bridge-ros2dds's publication caches


class CdrMessages:
    """The CDR messages of each record: the point (when there is a fix), the cloud, and
    /tf_static when TF_PERIOD_S has passed since it was last sent (what `bench` times)."""

    def __init__(self, ros2: Ros2Settings | None = None) -> None:
        ros2 = ros2 or Ros2Settings()
        self.encoder = Ros2Encoder(ros2.frame_id)
        self.transforms = list(ros2.transforms)
        self._tf_sent = -float("inf")

    def of_record(self, record: dict) -> list[tuple[str, bytes]]:
        seconds = record.get("stamp_host") or record.get("host_time")  # synced board time first
        best = record.get("position_mm")
        out = [] if best is None else [("point", self.encoder.point_stamped(best, seconds))]
        out.append(("targets", self.encoder.targets_cloud(record.get("targets") or [], seconds)))
        tf = self.tf_due()
        if tf is not None:
            out.append(("tf_static", tf))
        return out

    def tf_due(self) -> bytes | None:
        now = time.monotonic()
        if not self.transforms or now - self._tf_sent < TF_PERIOD_S:
            return None
        self._tf_sent = now
        return self.tf_message()

    def tf_message(self) -> bytes:
        return self.encoder.tf_message(self.transforms, time.time())


class ZenohRos2Sink:
    """Publish CDR PointStamped and PointCloud2 under the key prefix ``key_expr``."""

    def __init__(self, key_expr: str, ros2: Ros2Settings | None = None, config: Any = None):
        self.messages = CdrMessages(ros2)
        prefix = key_expr.strip("/")
        keys = {"point": f"{prefix}/point", "targets": f"{prefix}/targets"}
        if self.messages.transforms:
            keys["tf_static"] = "tf_static"
        self._session, self._publishers = open_publishers(keys, "APPLICATION_CDR", config)
        self.keys = keys
        self.failed = 0
        self._queryable = self._declare_tf_cache() if self.messages.transforms else None
        tf = self.messages.tf_due()
        if tf is not None:
            self._put("tf_static", tf)
        log.info("publishing ROS 2 CDR on Zenoh keys %s", ", ".join(self.keys.values()))

    def _put(self, name: str, payload: bytes) -> None:
        try:
            self._publishers[name].put(payload)
        except Exception as exc:  # zenoh.ZError: keep the run going, like UDP
            self.failed += 1
            if self.failed == 1 or self.failed % 1000 == 0:
                log.warning(
                    "Zenoh put on %s failed (%d so far): %s", self.keys[name], self.failed, exc
                )

    def _declare_tf_cache(self):
        """A queryable holding /tf_static, as the bridge's publication caches do."""
        import zenoh

        key = f"{PUB_CACHE_PREFIX}/{self._session.zid()}/tf_static"

        def answer(query) -> None:
            payload = self.messages.tf_message()
            query.reply(key, payload, encoding=zenoh.Encoding.APPLICATION_CDR)

        self.keys["tf_static_cache"] = key
        return self._session.declare_queryable(key, answer)

    def write(self, record: dict) -> None:
        for name, payload in self.messages.of_record(record):
            self._put(name, payload)

    def close(self) -> None:
        try:
            if self._queryable is not None:
                self._queryable.undeclare()
            for publisher in self._publishers.values():
                publisher.undeclare()
        finally:
            self._session.close()
