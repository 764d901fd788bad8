"""Live view through the Foxglove SDK's WebSocket server (extra ``foxglove``).

Topics: ``/spiel/scene`` (foxglove.SceneUpdate: the target as a sphere, the receivers as
small cubes, in metres in frame ``spiel``) and ``/spiel/position`` (the JSON records).
Binds 127.0.0.1 unless told otherwise: the server has no authentication.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

from spiel_edge.errors import ConfigError
from spiel_edge.outputs.mcap import POSITION_SCHEMA
from spiel_edge.outputs.udp import parse_host_port

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
FRAME_ID = "spiel"
SCENE_TOPIC = "/spiel/scene"
POSITION_TOPIC = "/spiel/position"
TARGET_SIZE_M = 0.03
RECEIVER_SIZE_M = 0.01


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


class FoxgloveSink:
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
        log.info("Foxglove live view on ws://%s:%d", host, self.port)

    def write(self, record: dict) -> None:
        m = self._m
        position = record.get("position_mm")
        if position is None:
            update = m.SceneUpdate(
                deletions=[m.SceneEntityDeletion(id="target")], entities=self._receiver_entities()
            )
        else:
            sphere = m.SpherePrimitive(
                pose=self._pose(position),
                color=m.Color(r=1.0, g=0.4, b=0.1, a=1.0),
                size=m.Vector3(x=TARGET_SIZE_M, y=TARGET_SIZE_M, z=TARGET_SIZE_M),
            )
            target = m.SceneEntity(frame_id=FRAME_ID, id="target", spheres=[sphere])
            update = m.SceneUpdate(entities=[target, *self._receiver_entities()])
        self._scene.log(update)
        self._records.log(record)

    def _receiver_entities(self) -> list:
        if not self._receivers:
            return []
        return [self._m.SceneEntity(frame_id=FRAME_ID, id="receivers", cubes=self._receivers)]

    def _pose(self, position_mm: Sequence[float]):
        m = self._m
        x, y, z = (float(v) / 1000.0 for v in position_mm)
        return m.Pose(position=m.Vector3(x=x, y=y, z=z), orientation=m.Quaternion(w=1.0))

    def _cube(self, position_mm: Sequence[float]):
        m = self._m
        return m.CubePrimitive(
            pose=self._pose(position_mm),
            color=m.Color(r=0.2, g=0.6, b=1.0, a=1.0),
            size=m.Vector3(x=RECEIVER_SIZE_M, y=RECEIVER_SIZE_M, z=RECEIVER_SIZE_M),
        )

    def close(self) -> None:
        self._server.stop()
