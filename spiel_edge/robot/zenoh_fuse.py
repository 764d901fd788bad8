"""``spiel-edge fuse``: boards on other computers (or processes), fused here, over Zenoh.

Each board's own process publishes its records (``spiel-edge run --port ... --zenoh KEY``:
JSON, with ``targets``, ``device_time_us`` and ``host_time``); this process subscribes to
every board's key of the robot file (``key``, default ``robot/<name>``), in peer mode or
through a router (Zenoh's own configuration: ``--connect``, ``--listen``, ``--mode``, a JSON5
file or ``$ZENOH_CONFIG``), and fuses them as ``run --robot`` does (robot/fusion.py). Zenoh is
the transport; nothing of our own is put on the wire.

Time: each board's stamps (``device_time_us``) are mapped to this computer's clock from the
records' arrival (robot/clock.py's lower envelope, which absorbs the network's delay). A
board whose computer's clock (its records' ``host_time``) is more than a second off this
one's is dropped with a warning (synchronise them: chrony or PTP), as is a board whose
records are not records. Per-board diagnostics ride in every fused record (``boards``).
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time

import numpy as np

from spiel_edge.errors import ConfigError
from spiel_edge.robot.clock import MAX_DISAGREEMENT_S, StampClock
from spiel_edge.robot.coast import CoastPolicy
from spiel_edge.robot.description import RobotSpec
from spiel_edge.robot.fusion import BoardReport, Fuser, OdometryBuffer, record_targets

log = logging.getLogger(__name__)

MAX_RECORD_BYTES = 1 << 20  # a board record is a few kB; anything larger is refused
BAD_RECORDS_LIMIT = 20  # this many unreadable records in a row: the board is dropped
QUEUE = 4096
ODOM = "\x00odom"  # the odometry subscriber's name in the queue (no board is named so)


def zenoh_config(connect=(), listen=(), mode: str | None = None, config: str | None = None):
    """A zenoh.Config: a JSON5 file (or ``$ZENOH_CONFIG``), then the endpoints and mode."""
    from spiel_edge.outputs.zenoh import _import_zenoh, load_config

    _import_zenoh()
    cfg = load_config(config)
    try:
        if mode:
            cfg.insert_json5("mode", json.dumps(mode))
        if connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if listen:
            cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    except Exception as exc:  # zenoh.ZError
        raise ConfigError(f"Zenoh configuration: {exc}") from exc
    return cfg


class ZenohFuse:
    """Subscribe to every board's key of ``robot``; fused records to ``sink``."""

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
        from spiel_edge.outputs.zenoh import _import_zenoh

        self.zenoh = _import_zenoh()
        self.robot = robot
        self.sink = sink
        self.queue: queue.Queue = queue.Queue(maxsize=QUEUE)
        self.odometry = OdometryBuffer()  # the robot's pose in odom, when odom_key is given
        self.odom_bad = 0
        self.fuser = Fuser(
            {b.name: b.mount for b in robot.boards},
            period_s=robot.trigger.period_ms / 1000.0,
            spec=spec or robot.track_spec(),
            frame_id=robot.frame_id,
            field_of_view_deg={b.name: b.field_of_view_deg for b in robot.boards},
            coast=CoastPolicy.from_robot(robot),
            track=track,
            odometry=None if odom_key is None else self.odometry,
        )
        self.clocks = {b.name: StampClock() for b in robot.boards}
        self.synced: dict[str, bool] = {}  # per board: its records carry stamp_host
        self.bad = dict.fromkeys(self.clocks, 0)
        self.dropped: dict[str, str] = {}
        self.overflow = 0
        self.records = 0
        self.latencies_ms: list[float] = []
        try:
            self.session = self.zenoh.open(config if config is not None else zenoh_config())
        except Exception as exc:
            raise ConfigError(f"fuse: cannot open a Zenoh session: {exc}") from exc
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
            raise ConfigError(f"fuse: cannot subscribe: {exc}") from exc
        log.info("fusing %s", ", ".join(f"{b.name} on {b.key}" for b in robot.boards))

    def _callback(self, name: str):
        def on_sample(sample) -> None:  # Zenoh's thread: hand over, nothing more
            arrived = time.time()
            try:
                self.queue.put_nowait((name, sample.payload.to_bytes(), arrived))
            except queue.Full:
                self.overflow += 1

        return on_sample

    def run(
        self, stop: threading.Event, *, frames: int | None = None, idle_s: float | None = None
    ) -> int:
        """Fuse until ``stop``, ``frames`` records, or ``idle_s`` without a board record once
        records came."""
        last = None
        while not stop.is_set():
            try:
                name, payload, arrived = self.queue.get(timeout=0.05)
            except queue.Empty:
                if idle_s is not None and last is not None and time.monotonic() - last > idle_s:
                    break
                continue
            last = time.monotonic()
            if name == ODOM:
                self._odom(payload, arrived)
                continue
            if name in self.dropped:
                continue
            report = self._report(name, payload, arrived)
            if report is None:
                continue
            for record in self.fuser.add(report):
                self._write(record)
            if frames is not None and self.records >= frames:
                break
        if frames is None or self.records < frames:
            for record in self.fuser.flush():
                self._write(record)
        return self.records

    def _report(self, name: str, payload: bytes, arrived: float) -> BoardReport | None:
        try:
            if len(payload) > MAX_RECORD_BYTES:
                raise ValueError(f"{len(payload)} bytes")
            record = json.loads(payload)
            stamp = float(record["device_time_us"]) / 1e6
            remote = float(record["host_time"])
            if not (np.isfinite(stamp) and np.isfinite(remote)):
                raise ValueError("non-finite time")
        except (ValueError, KeyError, TypeError) as exc:
            self.bad[name] += 1
            if self.bad[name] >= BAD_RECORDS_LIMIT:
                self._drop(name, f"its messages are not spiel-edge records ({exc})")
            return None
        self.bad[name] = 0
        if abs(arrived - remote) > MAX_DISAGREEMENT_S:
            self._drop(
                name,
                f"its computer's clock is {remote - arrived:+.2f} s off this one's "
                "(synchronise them: chrony or PTP)",
            )
            return None
        synced = record.get("stamp_host")  # protocol 2: the board's time on its host's clock
        synced = isinstance(synced, (int, float)) and np.isfinite(synced) and float(synced)
        if synced:
            stamp = synced  # its host's clock, mapped to this one's below
        if bool(synced) != self.synced.get(name, False):  # another time axis: learn it afresh
            self.synced[name] = bool(synced)
            self.clocks[name] = StampClock()
        clock = self.clocks[name]
        clock.observe(stamp, arrived)
        report = BoardReport(
            name,
            clock.to_host(stamp),
            record_targets(record),
            acquisition=int(record.get("acquisition", -1)),
            device_time_us=int(record["device_time_us"]),
            crosstalk=list(record.get("crosstalk") or []),
            error=record.get("reason") if record.get("error") else None,
            acquired_unix=remote,  # the acquisition's end on its own computer
            received_unix=arrived,  # its record's arrival here
        )
        return report

    def _odom(self, payload: bytes, arrived: float) -> None:
        """An odometry message: JSON ``{"stamp": Unix s, "x": m, "y": m, "yaw": rad}`` (the
        robot's planar pose in odom); its stamp is used when within a second of its arrival."""
        try:
            msg = json.loads(payload)
            x, y, yaw = (float(msg[k]) for k in ("x", "y", "yaw"))
            stamp = float(msg.get("stamp", arrived))
        except (ValueError, KeyError, TypeError, AttributeError):
            stamp, x, y, yaw = float("nan"), 0.0, 0.0, 0.0
        t = stamp if abs(stamp - arrived) <= MAX_DISAGREEMENT_S else arrived
        if not self.odometry.add(t, 1000.0 * x, 1000.0 * y, yaw):
            self.odom_bad += 1
            if self.odom_bad in (1, 100, 10000):
                log.warning(
                    "odometry: %d messages not used (malformed or out of order)", self.odom_bad
                )

    def _drop(self, name: str, why: str) -> None:
        self.dropped[name] = why
        self.fuser.drop(name)
        log.warning("board %s dropped, the others go on: %s", name, why)

    def _write(self, record: dict) -> None:
        now = time.time()
        acquired = [b.get("acquired") for b in record["boards"].values()]
        acquired = [a for a in acquired if a is not None]
        if acquired:
            latency = (now - max(acquired)) * 1e3
            record["latency_ms"] = round(latency, 3)
            self.latencies_ms.append(latency)
        received = [b["received"] for b in record["boards"].values() if "received" in b]
        if received:  # the fuser's share: from the last board record's arrival to the write
            record["fuser_ms"] = round((now - max(received)) * 1e3, 3)
        for name, why in self.dropped.items():
            record.setdefault("dropped", {})[name] = why
        self.sink.write(record)
        self.records += 1

    def summary(self) -> str:
        lat = np.array(self.latencies_ms)
        latency = (
            f"; latency after the last board's acquisition median {np.median(lat):.2f} ms, "
            f"p95 {np.percentile(lat, 95):.2f} ms"
            if lat.size
            else ""
        )
        boards = "; ".join(
            f"{n}: dropped ({self.dropped[n]})"
            if n in self.dropped
            else f"{n}: {s['reports']} records, {s['targets']} targets"
            for n, s in self.fuser.stats.items()
        )
        extra = f"; {self.overflow} records lost (queue full)" if self.overflow else ""
        return f"{self.records} fused records{latency}; {boards}{extra}"

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
