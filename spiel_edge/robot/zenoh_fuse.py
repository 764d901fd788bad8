"""``spiel-edge fuse``: boards on other computers (or processes), fused here, over Zenoh.

Each board's own process publishes its records (``spiel-edge run --port ... --zenoh KEY``:
JSON, with ``targets``, ``device_time_us`` and ``host_time``); this process subscribes to
every board's key of the robot file (``key``, default ``robot/<name>``), in peer mode or
through a router (Zenoh's own configuration: ``--connect``, ``--listen``, ``--mode``, a JSON5
file or ``$ZENOH_CONFIG``), and fuses them as ``run --robot`` does (robot/fusion.py). Zenoh is
the transport; nothing of our own is put on the wire.

What happens to a record once here (clocks, drops, fusion, diagnostics, odometry) is
robot/record_fuse.py's, shared with the offline replay of recorded records.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time

from spiel_edge.errors import ConfigError
from spiel_edge.outputs.zenoh import zenoh_reason
from spiel_edge.robot.description import RobotSpec
from spiel_edge.robot.record_fuse import MAX_RECORD_BYTES, RecordFuse

log = logging.getLogger(__name__)

QUEUE = 4096
ODOM = "\x00odom"  # the odometry subscriber's name in the queue (no board is named so)


def zenoh_config(connect=(), listen=(), mode: str | None = None, config: str | None = None):
    """A zenoh.Config: a JSON5 file (or ``$ZENOH_CONFIG``), then the endpoints and mode;
    confined to loopback where none of them says otherwise (docs/security.md)."""
    from spiel_edge.outputs.zenoh import confine_to_loopback, import_zenoh, load_config

    import_zenoh()
    cfg = load_config(config)
    try:
        if mode:
            cfg.insert_json5("mode", json.dumps(mode))
        if connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if listen:
            cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
        confine_to_loopback(cfg)
    except Exception as exc:  # zenoh.ZError
        raise ConfigError(f"Zenoh configuration: {zenoh_reason(exc)}") from exc
    return cfg


def verifiers(robot: RobotSpec) -> dict:
    """Per board with an ``auth_key_file``: its record_auth.Verifier (ConfigError in one line
    when a key file is missing, unreadable, readable by every user, or not a key)."""
    from spiel_edge.outputs.record_auth import Verifier, load_key

    out = {}
    for b in robot.boards:
        path = robot.auth_key_path(b)
        if path is not None:
            out[b.name] = Verifier(load_key(path, f"board {b.name!r} auth_key_file"), b.key)
    return out


class ZenohFuse(RecordFuse):
    """Subscribe to every board's key of ``robot``; fused records to ``sink``. ``odom_key``:
    the robot's odometry on Zenoh (JSON, or nav_msgs/msg/Odometry in CDR as rmw_zenoh
    publishes it: a key expression such as ``*/odom/**``)."""

    def __init__(
        self,
        robot: RobotSpec,
        sink,
        *,
        config=None,
        track: bool = True,
        spec=None,
        odom_key: str | None = None,
    ):
        from spiel_edge.outputs.zenoh import import_zenoh

        self.zenoh = import_zenoh()
        super().__init__(robot, sink, track=track, spec=spec, odom_messages=odom_key is not None)
        self.queue: queue.Queue = queue.Queue(maxsize=QUEUE)
        self.overflow = 0
        # per board (and odometry): at most its share of the queue, so one flooding peer
        # costs its own records, not the others'
        self.share = QUEUE // (len(robot.boards) + 1)
        self.queued = dict.fromkeys([*(b.name for b in robot.boards), ODOM], 0)
        self._queued_lock = threading.Lock()
        self.verifiers = verifiers(robot)  # before the session: a bad key file opens nothing
        try:
            self.session = self.zenoh.open(config if config is not None else zenoh_config())
        except Exception as exc:
            raise ConfigError(f"fuse: cannot open a Zenoh session: {zenoh_reason(exc)}") from exc
        self.subscribers = []
        try:
            for b in robot.boards:
                self.subscribers.append(
                    self.session.declare_subscriber(b.key, self._callback(b.name))
                )
            if odom_key is not None:
                self.subscribers.append(
                    self.session.declare_subscriber(odom_key, self._callback(ODOM))
                )
        except Exception as exc:
            self.close()
            raise ConfigError(f"fuse: cannot subscribe: {zenoh_reason(exc)}") from exc
        log.info("fusing %s", ", ".join(f"{b.name} on {b.key}" for b in robot.boards))
        unsigned = [b.name for b in robot.boards if b.name not in self.verifiers]
        if self.verifiers and unsigned:
            log.warning("boards %s have no auth_key_file: any peer can publish as them", unsigned)

    def _callback(self, name: str):
        verifier = self.verifiers.get(name)

        def on_sample(sample) -> None:  # Zenoh's thread: check the origin, hand over
            arrived = time.time()
            payload = sample.payload.to_bytes()
            refused = None
            if len(payload) > MAX_RECORD_BYTES:
                refused, payload = "too large", b""
            elif verifier is not None:  # a forged flood never reaches the queue
                attached = sample.attachment
                why = verifier.check(payload, None if attached is None else attached.to_bytes())
                if why:
                    self.count_refused(name, why)
                    return
            with self._queued_lock:
                if self.queued[name] >= self.share:
                    full = True
                else:
                    full = False
                    self.queued[name] += 1
            if full:
                self.count_refused(name, "flood")
                return
            try:
                self.queue.put_nowait((name, payload, arrived, refused))
            except queue.Full:
                self.overflow += 1
                with self._queued_lock:
                    self.queued[name] -= 1

        return on_sample

    def run(
        self, stop: threading.Event, *, frames: int | None = None, idle_s: float | None = None
    ) -> int:
        """Fuse until ``stop``, ``frames`` records, or ``idle_s`` without a board record once
        records came."""
        last = None
        while not stop.is_set():
            try:
                name, payload, arrived, refused = self.queue.get(timeout=0.05)
            except queue.Empty:
                if idle_s is not None and last is not None and time.monotonic() - last > idle_s:
                    break
                continue
            last = time.monotonic()
            with self._queued_lock:
                self.queued[name] -= 1
            if name == ODOM:
                if refused is None:
                    self.handle_odometry(payload, arrived)
                continue
            self.handle(name, payload, arrived, refused)
            if frames is not None and self.records >= frames:
                break
        if frames is None or self.records < frames:
            self.finish()
        return self.records

    def summary(self) -> str:
        extra = f"; {self.overflow} records lost (queue full)" if self.overflow else ""
        return super().summary() + extra

    def close(self) -> None:
        for sub in self.subscribers:
            try:
                sub.undeclare()
            except Exception as exc:  # zenoh.ZError on a closing session
                log.debug("undeclare: %s", exc)
        self.subscribers = []
        try:
            self.session.close()
        except Exception as exc:
            log.debug("zenoh close: %s", exc)
