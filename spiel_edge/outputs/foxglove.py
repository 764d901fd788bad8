"""Live view through the Foxglove SDK's WebSocket server (extra ``foxglove``).

Topics: ``/spiel/scene`` (foxglove.SceneUpdate in metres in frame ``spiel``: every target as a
sphere inside its translucent 95 % uncertainty ellipsoid, every track as a sphere with its id
and a short trail, the receivers as small cubes; the best position alone as before when a
record has no ``targets``) and ``/spiel/position`` (the JSON records).
Binds 127.0.0.1 unless told otherwise: the server has no authentication.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

from spiel_edge.errors import ConfigError
from spiel_edge.outputs.scene_view import Trails, ellipsoid
from spiel_edge.outputs.sink import Sink
from spiel_edge.outputs.udp import parse_host_port
from spiel_edge.recordings.mcap_writer import POSITION_SCHEMA

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
FRAME_ID = "spiel"
SCENE_TOPIC = "/spiel/scene"
POSITION_TOPIC = "/spiel/position"
TARGET_SIZE_M = 0.03
RECEIVER_SIZE_M = 0.01
TRACK_SIZE_M = 0.015
TRACK_COLORS = ((0.2, 0.8, 0.3), (0.9, 0.8, 0.1), (0.7, 0.3, 0.9), (0.1, 0.8, 0.9), (1.0, 0.4, 0.7))


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

    def __init__(
        self,
        bind: str = f"{DEFAULT_HOST}:{DEFAULT_PORT}",
        *,
        receivers_mm: Sequence[Sequence[float]] | None = None,
    ):
        foxglove, self._m = _import_foxglove()
        host, port = parse_host_port(bind, default_host=DEFAULT_HOST, what="--foxglove")
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
        self._receivers = [self._cube(p) for p in ([] if receivers_mm is None else receivers_mm)]
        self._trails = Trails()
        self._shown: set[str] = set()
        log.info("Foxglove live view on ws://%s:%d", host, self.port)

    def write(self, record: dict) -> None:
        shown: set[str] = set()
        entities = [*self._target_entities(record, shown), *self._track_entities(record, shown)]
        entities += self._receiver_entities()
        gone = [self._m.SceneEntityDeletion(id=i) for i in sorted(self._shown - shown)]
        self._shown = shown
        self._scene.log(self._m.SceneUpdate(deletions=gone, entities=entities))
        self._records.log(record)

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
            out.append(m.SceneEntity(frame_id=FRAME_ID, id=entity_id, spheres=spheres))
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
                    frame_id=FRAME_ID,
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
        return [self._m.SceneEntity(frame_id=FRAME_ID, id="receivers", cubes=self._receivers)]

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
