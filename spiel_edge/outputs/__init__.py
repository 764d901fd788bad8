"""Where records go: one Sink per destination (``ndjson``, ``udp``, ``foxglove``, ``zenoh``,
the MCAP recordings of :mod:`spiel_edge.recordings`), several at once through ``fanout``."""

from spiel_edge.outputs.fanout import MultiSink, Sink, check_outputs, open_outputs, recording_path

__all__ = ["MultiSink", "Sink", "check_outputs", "open_outputs", "recording_path"]
