"""Live view through the Foxglove SDK's WebSocket server (extra ``foxglove``), laid out as a
ros2 recording: the same ROS 2 CDR channels as ``--record-profile ros2`` (``/spiel/point``,
``/spiel/targets``, ``/spiel/tracks``, ``/spiel/range``, ``/diagnostics``, ``/tf_static``,
schemas ``ros2msg``; messages/ros2_messages.py), plus

* ``/tf``: foxglove.FrameTransforms, the same transforms as /tf_static (mount and optical
  frame), sent at start and every TF_PERIOD_S so a client that connects later has them;
* ``/spiel/scene``: foxglove.SceneUpdate in metres in the messages' frame
  (``<--frame-id>_optical``): every target as a sphere inside its translucent 95 % uncertainty
  ellipsoid, every track as a sphere with its id and a short trail, the receivers as small
  cubes; the best position alone when a record has no ``targets``;
* ``/spiel/position``: the JSON records;
* ``/spiel/echogram``: foxglove.RawImage (rgb8), the waterfall of the last 128 A-scans with
  the echoes marked (outputs/echogram.py; the layout packaging/foxglove/spiel-edge.json).

Binds 127.0.0.1 unless told otherwise: the server has no authentication.
"""

from __future__ import annotations

import ipaddress
import logging
import time
from collections.abc import Sequence

from spiel_edge.errors import ConfigError
from spiel_edge.outputs.scene_view import Trails, ellipsoid
from spiel_edge.outputs.sink import ACQUISITIONS, STATUS, VIEW, Sink
from spiel_edge.outputs.udp import parse_host_port
from spiel_edge.recordings.mcap_writer import POSITION_SCHEMA

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
FRAME_ID = "spiel_optical"  # the messages' frame for the default --frame-id
TF_PERIOD_S = 1.0
TF_TOPIC = "/tf"
SCENE_TOPIC = "/spiel/scene"
POSITION_TOPIC = "/spiel/position"
ECHOGRAM_TOPIC = "/spiel/echogram"
TARGET_SIZE_M = 0.03
RECEIVER_SIZE_M = 0.01
TRACK_SIZE_M = 0.015
TRACK_COLORS = ((0.2, 0.8, 0.3), (0.9, 0.8, 0.1), (0.7, 0.3, 0.9), (0.1, 0.8, 0.9), (1.0, 0.4, 0.7))


def is_loopback(host: str) -> bool:
    """``host`` is this computer only: a loopback address or ``localhost``."""
    if host.lower() in ("localhost", "localhost.localdomain"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a name: it may well resolve beyond this computer


def _import_foxglove():
    try:
        import foxglove

        try:
            from foxglove import messages
        except ImportError:  # foxglove-sdk before messages was split from schemas
            from foxglove import schemas as messages
    except ImportError as exc:
        raise ConfigError(
            f"--foxglove needs the Foxglove SDK: pip install 'spiel-edge[foxglove]' ({exc})"
        ) from exc
    return foxglove, messages


class FoxgloveSink(Sink):
    """Serve records on a Foxglove WebSocket at ``[HOST:]PORT`` (port 0 picks a free one)."""

    capabilities = frozenset({ACQUISITIONS, STATUS, VIEW})  # the echogram draws the raw samples

    def __init__(
        self,
        bind: str = f"{DEFAULT_HOST}:{DEFAULT_PORT}",
        *,
        receivers_mm: Sequence[Sequence[float]] | None = None,
        ros2=None,
    ):
        from spiel_edge.messages import ros2_messages as rm
        from spiel_edge.messages import ros2_types
        from spiel_edge.recordings.ros2_mcap import qos_yaml, topic_name

        foxglove, self._m = _import_foxglove()
        self.messages = rm.Ros2Messages(ros2)
        self.frame_id = self.messages.frame_id
        host, port = parse_host_port(bind, default_host=DEFAULT_HOST, what="--foxglove")
        if not is_loopback(host):
            log.warning(
                "--foxglove %s: the live view (no authentication) is reachable from other "
                "computers; the default binds 127.0.0.1 only (docs/security.md)",
                host,
            )
        self._context = foxglove.Context()  # our own: no clash with other SDK users in-process
        try:
            self._server = foxglove.start_server(
                name="spiel-edge", host=host, port=port, context=self._context
            )
        except Exception as exc:  # the SDK raises its own error types (address in use, ...)
            raise ConfigError(
                f"--foxglove {bind!r}: cannot start the WebSocket server: {exc}"
            ) from exc
        self.port = self._server.port
        self._scene = foxglove.channels.SceneUpdateChannel(SCENE_TOPIC, context=self._context)
        self._records = foxglove.Channel(
            POSITION_TOPIC, schema=POSITION_SCHEMA, context=self._context
        )
        self._ros2 = {}
        for name, type_name in rm.TOPICS.items():
            schema = foxglove.Schema(
                name=type_name,
                encoding="ros2msg",
                data=ros2_types.rosbag2_definition(type_name).encode(),
            )
            self._ros2[name] = foxglove.Channel(
                topic_name(name),
                schema=schema,
                message_encoding="cdr",
                context=self._context,
                metadata={
                    "offered_qos_profiles": qos_yaml(name in rm.LATCHED),
                    "topic_type_hash": ros2_types.type_hash(type_name),
                },
            )
        self._tf_channel = foxglove.channels.FrameTransformsChannel(TF_TOPIC, context=self._context)
        from spiel_edge.outputs.echogram import Echogram

        self._echogram = Echogram()
        self._echogram_channel = foxglove.channels.RawImageChannel(
            ECHOGRAM_TOPIC, context=self._context
        )
        self._acquisition = None  # the raw samples of the record to come
        self._next_tf = 0.0
        self._send_transforms()
        self._receivers = [self._cube(p) for p in ([] if receivers_mm is None else receivers_mm)]
        self._trails = Trails()
        self._shown: set[str] = set()
        self.view_line = f"Foxglove live view on ws://{host}:{self.port}"
        log.info("%s", self.view_line)

    def set_status_provider(self, provider) -> None:
        self.messages.status_provider = provider

    def _send_transforms(self) -> None:
        """/tf_static (CDR) and /tf (foxglove.FrameTransforms), now and every TF_PERIOD_S: a
        WebSocket client that connects later gets no cached message."""
        now = time.monotonic()
        if now < self._next_tf:
            return
        self._next_tf = now + TF_PERIOD_S
        m = self._m
        self._ros2["/tf_static"].log(self.messages.tf_message())
        self._tf_channel.log(
            m.FrameTransforms(
                transforms=[
                    m.FrameTransform(
                        parent_frame_id=tf.parent,
                        child_frame_id=tf.child,
                        translation=m.Vector3(
                            x=tf.translation_m[0], y=tf.translation_m[1], z=tf.translation_m[2]
                        ),
                        rotation=m.Quaternion(
                            x=tf.rotation_xyzw[0],
                            y=tf.rotation_xyzw[1],
                            z=tf.rotation_xyzw[2],
                            w=tf.rotation_xyzw[3],
                        ),
                    )
                    for tf in self.messages.transforms
                ]
            )
        )

    def write(self, record: dict) -> None:
        for name, payload in self.messages.of_record(record):
            self._ros2[name].log(payload)
        self._send_transforms()
        shown: set[str] = set()
        entities = [*self._target_entities(record, shown), *self._track_entities(record, shown)]
        entities += self._receiver_entities()
        gone = [self._m.SceneEntityDeletion(id=i) for i in sorted(self._shown - shown)]
        self._shown = shown
        self._scene.log(self._m.SceneUpdate(deletions=gone, entities=entities))
        self._records.log(record)
        self._send_echogram(record)

    def write_acquisition(self, acquisition: dict, frames) -> None:
        self._acquisition = (frames, acquisition.get("background"))

    def _send_echogram(self, record: dict) -> None:
        if self._acquisition is None or not isinstance(record.get("echoes"), list):
            return
        frames, background = self._acquisition
        self._acquisition = None
        image = self._echogram.add(frames, background, record["echoes"], record.get("matched"))
        rows, width = image.shape[:2]
        self._echogram_channel.log(
            self._m.RawImage(
                frame_id="spiel_echogram",
                width=width,
                height=rows,
                encoding="rgb8",
                step=3 * width,
                data=image.tobytes(),
            )
        )

    def _target_entities(self, record: dict, shown: set[str]) -> list:
        m = self._m
        targets = record.get("targets") or []
        if not targets and record.get("position_mm") is not None:
            targets = [{"position_mm": record["position_mm"]}]
        out = []
        for k, target in enumerate(targets):
            spheres = [self._sphere(target["position_mm"], TARGET_SIZE_M, (1.0, 0.4, 0.1), 1.0)]
            if target.get("covariance_mm2") is not None:
                size, q = ellipsoid(target["covariance_mm2"])
                shell = m.SpherePrimitive(
                    pose=self._pose(target["position_mm"], q),
                    color=m.Color(r=1.0, g=0.4, b=0.1, a=0.25),
                    size=m.Vector3(x=size[0] / 1e3, y=size[1] / 1e3, z=size[2] / 1e3),
                )
                spheres.append(shell)
            entity_id = "target" if k == 0 else f"target/{k}"
            shown.add(entity_id)
            out.append(m.SceneEntity(frame_id=self.frame_id, id=entity_id, spheres=spheres))
        return out

    def _track_entities(self, record: dict, shown: set[str]) -> list:
        m = self._m
        tracks = record.get("tracks") or []
        out = []
        for track_id, trail in self._trails.update(tracks).items():
            rgb = TRACK_COLORS[track_id % len(TRACK_COLORS)]
            color = m.Color(r=rgb[0], g=rgb[1], b=rgb[2], a=1.0)
            line = m.LinePrimitive(
                type=m.LinePrimitiveLineType.LineStrip,
                pose=self._pose([0.0, 0.0, 0.0]),
                thickness=2.0,
                scale_invariant=True,
                points=[m.Point3(x=p[0] / 1e3, y=p[1] / 1e3, z=p[2] / 1e3) for p in trail],
                color=color,
            )
            label = m.TextPrimitive(
                pose=self._pose([trail[-1][0], trail[-1][1], trail[-1][2] + 15.0]),
                billboard=True,
                font_size=14.0,
                scale_invariant=True,
                color=color,
                text=str(track_id),
            )
            shown.add(f"track/{track_id}")
            out.append(
                m.SceneEntity(
                    frame_id=self.frame_id,
                    id=f"track/{track_id}",
                    spheres=[self._sphere(trail[-1], TRACK_SIZE_M, rgb, 0.9)],
                    lines=[line],
                    texts=[label],
                )
            )
        return out

    def _sphere(self, position_mm, size_m: float, rgb, alpha: float):
        m = self._m
        return m.SpherePrimitive(
            pose=self._pose(position_mm),
            color=m.Color(r=rgb[0], g=rgb[1], b=rgb[2], a=alpha),
            size=m.Vector3(x=size_m, y=size_m, z=size_m),
        )

    def _receiver_entities(self) -> list:
        if not self._receivers:
            return []
        return [self._m.SceneEntity(frame_id=self.frame_id, id="receivers", cubes=self._receivers)]

    def _pose(self, position_mm: Sequence[float], q: Sequence[float] = (0.0, 0.0, 0.0, 1.0)):
        m = self._m
        x, y, z = (float(v) / 1000.0 for v in position_mm)
        orientation = m.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
        return m.Pose(position=m.Vector3(x=x, y=y, z=z), orientation=orientation)

    def _cube(self, position_mm: Sequence[float]):
        m = self._m
        return m.CubePrimitive(
            pose=self._pose(position_mm),
            color=m.Color(r=0.2, g=0.6, b=1.0, a=1.0),
            size=m.Vector3(x=RECEIVER_SIZE_M, y=RECEIVER_SIZE_M, z=RECEIVER_SIZE_M),
        )

    def close(self) -> None:
        self._server.stop()
