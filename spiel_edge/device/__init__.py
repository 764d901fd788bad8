"""The host side of a board: session (handshake, requests, stream, reconnect) over a link."""

from spiel_edge.device.session import DeviceSession, SessionCounters
from spiel_edge.device.stream import LiveAcquisition, StreamTracker

__all__ = ["DeviceSession", "LiveAcquisition", "SessionCounters", "StreamTracker"]
