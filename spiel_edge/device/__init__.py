"""The host side of a board: session (handshake, requests, stream, reconnect) over a link."""

from spiel_edge.device.acquisitions import LiveAcquisition, StreamAssembly
from spiel_edge.device.session import DeviceSession, SessionCounters

__all__ = ["DeviceSession", "LiveAcquisition", "SessionCounters", "StreamAssembly"]
