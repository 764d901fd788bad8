"""Where records go: one Sink (``sink``) per destination (``ndjson``, ``udp``, ``foxglove``,
``zenoh``, the MCAP recordings of :mod:`spiel_edge.recordings`), several at once through
``fanout``."""

from spiel_edge.outputs.fanout import MultiSink, check_outputs, open_outputs, recording_path
from spiel_edge.outputs.sink import Sink

__all__ = ["MultiSink", "Sink", "check_outputs", "open_outputs", "recording_path"]
