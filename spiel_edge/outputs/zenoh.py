"""Fleet publishing over Zenoh (extra ``zenoh``): each record as JSON on one key expression.

The session uses Zenoh's own configuration: a JSON5 file given here, or ``$ZENOH_CONFIG``,
else the defaults (peer mode, multicast scouting on the local network).
Congestion control drops records rather than blocking the run loop.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

from spiel_edge.errors import ConfigError
from spiel_edge.outputs.sink import Sink

log = logging.getLogger(__name__)


def _import_zenoh():
    try:
        import zenoh
    except ImportError as exc:
        raise ConfigError(f"--zenoh needs Zenoh: pip install 'spiel-edge[zenoh]' ({exc})") from exc
    return zenoh


def load_config(config: Any = None):
    """A zenoh.Config from a Config, a JSON5 file path, ``$ZENOH_CONFIG`` or the defaults."""
    zenoh = _import_zenoh()
    if isinstance(config, zenoh.Config):
        return config
    path = config or os.environ.get("ZENOH_CONFIG")
    if not path:
        return zenoh.Config()
    try:
        return zenoh.Config.from_file(str(Path(path)))
    except Exception as exc:  # zenoh.ZError and I/O errors alike
        raise ConfigError(f"Zenoh config {path}: {exc}") from exc


def open_publishers(keys: dict[str, str], encoding: str, config: Any = None):
    """(session, {name: publisher}) for the key expressions ``keys``; ``encoding`` names a
    ``zenoh.Encoding`` attribute. Bad keys or an unreachable network: ConfigError."""
    zenoh = _import_zenoh()
    exprs = {}
    for name, key in keys.items():
        try:
            exprs[name] = zenoh.KeyExpr(key)
        except Exception as exc:
            raise ConfigError(f"--zenoh {key!r} is not a valid key expression: {exc}") from exc
    try:
        session = zenoh.open(load_config(config))
    except ConfigError:
        raise
    except Exception as exc:
        raise ConfigError(f"--zenoh: cannot open a Zenoh session: {exc}") from exc
    publishers = {
        name: session.declare_publisher(
            expr,
            encoding=getattr(zenoh.Encoding, encoding),
            congestion_control=zenoh.CongestionControl.DROP,  # drop, never block the run loop
        )
        for name, expr in exprs.items()
    }
    return session, publishers


class ZenohSink(Sink):
    """Publish each record on ``key_expr`` (e.g. ``robots/r1/spiel/position``)."""

    def __init__(self, key_expr: str, config: Any = None):
        self._session, publishers = open_publishers(
            {"record": key_expr}, "APPLICATION_JSON", config
        )
        self._publisher = publishers["record"]
        self.key_expr = key_expr
        self.failed = 0
        log.info("publishing records on Zenoh key %s", self.key_expr)

    def write(self, record: dict) -> None:
        try:
            self._publisher.put(json.dumps(record, separators=(",", ":"), allow_nan=False))
        except Exception as exc:  # zenoh.ZError: keep the run going, like UDP
            self.failed += 1
            if self.failed == 1 or self.failed % 1000 == 0:
                log.warning(
                    "Zenoh put on %s failed (%d so far): %s", self.key_expr, self.failed, exc
                )

    def close(self) -> None:
        try:
            self._publisher.undeclare()
        finally:
            self._session.close()
