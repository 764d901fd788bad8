"""UDP datagrams, one compact JSON record each: the lightest way into another process or host.

Sending never blocks the run loop for long and never ends it: a failed send (network down,
buffer full) is counted and logged at most once per interval, and the next record is tried.
"""

from __future__ import annotations

import json
import logging
import socket
import time

from spiel_edge.errors import ConfigError
from spiel_edge.outputs.sink import Sink
from spiel_edge.safety.guard import shorten

log = logging.getLogger(__name__)

MAX_DATAGRAM = 65507  # largest UDP payload over IPv4
_LOG_EVERY_S = 10.0


def parse_host_port(
    text: str, *, default_host: str | None = None, what: str = "address"
) -> tuple[str, int]:
    """``HOST:PORT``, ``[v6]:PORT`` or (with a default host) ``PORT``; ConfigError otherwise."""
    text = text.strip()
    host, sep, port_text = text.rpartition(":")
    if not sep:
        host, port_text = "", text
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    host = host or (default_host or "")
    try:
        port = int(port_text)
    except ValueError:
        port = -1
    if not host or not 0 <= port <= 65535:
        form = "[HOST:]PORT" if default_host else "HOST:PORT"
        raise ConfigError(f"{what} {shorten(text)!r} is not {form} (port 0-65535)")
    return host, port


class UdpSink(Sink):
    """Send each record as one datagram to ``HOST:PORT`` (broadcast addresses allowed)."""

    def __init__(self, target: str, *, timeout_s: float = 0.05):
        host, port = parse_host_port(target, what="--udp")
        try:
            family, kind, proto, _, address = socket.getaddrinfo(
                host, port, type=socket.SOCK_DGRAM
            )[0]
        except socket.gaierror as exc:
            raise ConfigError(f"--udp {target!r}: cannot resolve {host!r}: {exc}") from exc
        self.address = address
        self._sock = socket.socket(family, kind, proto)
        self._sock.settimeout(timeout_s)
        if family == socket.AF_INET:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        self.sent = self.failed = 0
        self._last_log = -float("inf")

    def write(self, record: dict) -> None:
        data = json.dumps(record, separators=(",", ":"), allow_nan=False).encode()
        if len(data) > MAX_DATAGRAM:
            self._failed(f"record of {len(data)} bytes does not fit one datagram")
            return
        try:
            self._sock.sendto(data, self.address)
        except OSError as exc:  # timeouts included: drop the record, keep the sink
            self._failed(str(exc) or type(exc).__name__)
            return
        self.sent += 1

    def _failed(self, why: str) -> None:
        self.failed += 1
        now = time.monotonic()
        if now - self._last_log >= _LOG_EVERY_S:
            self._last_log = now
            log.warning(
                "UDP output to %s: %s (%d records dropped so far)", self.address, why, self.failed
            )

    def close(self) -> None:
        self._sock.close()
