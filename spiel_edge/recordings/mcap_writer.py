"""MCAP recordings: raw acquisitions and positions on separate JSON channels, and replay.

Channels (message encoding ``json``, schemas ``jsonschema``, so Foxglove opens the file and
``mcap``/rosbag2 tooling lists it):

* ``/spiel/acquisition``: one raw acquisition (``frames``: channels x samples) plus the
  acquisition's metadata (``seq``, timestamps, ...);
* ``/spiel/background``: the target-free capture, written when it changes (and again every
  16 acquisitions; each acquisition names its ``background_crc``, the CRC-32 of that message); it applies to the
  acquisitions that follow it;
* ``/spiel/position``: one pipeline record per acquisition, with its ``targets`` and, when
  tracking, ``tracks`` (docs/tracking.md).

The file is finalized (summary, indexes) on :meth:`McapSink.close`; the sink installs no
signal handler (the command line turns INT, TERM and HUP into a clean stop that closes it). A
file cut short by a hard kill is still replayed up to its last complete chunk.
"""

from __future__ import annotations

import json
import logging
import threading
import time
import zlib
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.writer import CompressionType, Writer

from spiel_edge import __version__
from spiel_edge.recordings.mcap_reader import ACQUISITION_TOPIC, BACKGROUND_TOPIC, POSITION_TOPIC
from spiel_edge.safety.guard import open_exclusive

log = logging.getLogger(__name__)

MCAP_PROFILE = ""  # no ROS message definitions: plain JSON with JSON schemas
CHUNK_SIZE = (
    32 * 1024
)  # about 20 acquisitions of 4 x 64: the most a hard kill or one bad byte loses
BACKGROUND_EVERY = 16  # the background is written again this often, so damage loses little

_FRAMES = {
    "type": "array",
    "items": {"type": "array", "items": {"type": ["number", "null"]}},
    "description": "channels x samples, raw counts",
}
ACQUISITION_SCHEMA = {
    "title": "spiel_edge.Acquisition",
    "type": "object",
    "properties": {
        "seq": {"type": "integer"},
        "timestamp_ns": {"type": "integer"},
        "frames": _FRAMES,
    },
    "required": ["frames"],
}
BACKGROUND_SCHEMA = {
    "title": "spiel_edge.Background",
    "type": "object",
    "properties": {"frames": _FRAMES},
    "required": ["frames"],
}
_VECTOR3 = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
_COVARIANCE = {"type": "array", "items": _VECTOR3, "minItems": 3, "maxItems": 3}
TARGET_SCHEMA = {
    "type": "object",
    "properties": {
        "position_mm": _VECTOR3,
        "covariance_mm2": _COVARIANCE,
        "residual_mm": {"type": "number"},
        "matched": {"type": "array", "items": {"type": ["integer", "null"]}},
        "score": {"type": "number"},
        "track_id": {"type": "integer"},
    },
}
TRACK_SCHEMA = {
    "type": "object",
    "properties": {
        "track_id": {"type": "integer"},
        "position_mm": _VECTOR3,
        "velocity_mm_s": _VECTOR3,
        "covariance_mm2": _COVARIANCE,
        "velocity_covariance_mm2_s2": _COVARIANCE,
        "age": {"type": "integer"},
        "hits": {"type": "integer"},
    },
}
POSITION_SCHEMA = {
    "title": "spiel_edge.Position",
    "type": "object",
    "properties": {
        "position_mm": {
            "type": ["array", "null"],
            "items": {"type": "number"},
            "minItems": 3,
            "maxItems": 3,
        },
        "reason": {"type": ["string", "null"]},
        "residual_mm": {"type": ["number", "null"]},
        "echoes": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}},
        "matched": {"type": "array", "items": {"type": ["integer", "null"]}},
        "targets": {"type": "array", "items": TARGET_SCHEMA},
        "tracks": {"type": "array", "items": TRACK_SCHEMA},
    },
}


class McapSink:
    """Record acquisitions and records to ``path`` (overwritten); always call close().

    An output (outputs/sink.py's contract, kept without importing it: recordings sit below
    outputs): it keeps the acquisitions and owns its file."""

    capabilities = frozenset({"acquisitions", "file"})  # outputs.sink.ACQUISITIONS, FILE
    hold = False  # every write goes straight to the MCAP writer; nothing to flush
    view_line = ""
    owns_file = True
    wants_acquisitions = True

    def batch(self) -> None:
        """Not HOLD: nothing to hold."""

    def parts(self) -> list:
        return [self]

    def set_status_provider(self, provider) -> None:
        """No /diagnostics in a recording."""

    def flush(self) -> None:
        """Nothing held."""

    @property
    def alive(self) -> bool:
        return not self.closed

    def __init__(
        self,
        path: str | Path,
        *,
        metadata: dict[str, Any] | None = None,
        chunk_size: int = CHUNK_SIZE,
        compression: str = "zstd",
        exclusive: bool = False,
    ):
        self.path = Path(path)
        # exclusive: never replace a file that appeared since the command checked its outputs
        self._fh: IO[bytes] = open_exclusive(self.path, force=not exclusive)
        self._writer = Writer(
            self._fh, chunk_size=chunk_size, compression=CompressionType[compression.upper()]
        )
        self._writer.start(profile=self.profile, library=f"spiel-edge {__version__}")
        self._channels = self._register_channels()
        self._writer.add_metadata(
            "spiel-edge",
            {"version": __version__, **{k: str(v) for k, v in (metadata or {}).items()}},
        )
        self._sequence = 0
        self._background: np.ndarray | None = None
        self._background_crc = 0
        self._background_chunk = -1
        self._lock = threading.RLock()  # close() may come from the signal watchdog
        self._since_background = 0
        self.closed = False
        self.counts = {"acquisitions": 0, "records": 0}
        # a replay's recording: log times are the capture times, so `ros2 bag play` paces it
        self.log_time_from_stamp = False

    profile = MCAP_PROFILE  # subclasses (recordings/ros2_mcap.py) change the encoding

    def _register_channels(self) -> dict[str, int]:
        return {
            topic: self._channel(topic, schema)
            for topic, schema in (
                (ACQUISITION_TOPIC, ACQUISITION_SCHEMA),
                (BACKGROUND_TOPIC, BACKGROUND_SCHEMA),
                (POSITION_TOPIC, POSITION_SCHEMA),
            )
        }

    def _channel(self, topic: str, schema: dict) -> int:
        schema_id = self._writer.register_schema(
            schema["title"], "jsonschema", json.dumps(schema).encode()
        )
        return self._writer.register_channel(topic, "json", schema_id)

    def write_acquisition(self, acquisition: dict, frames: np.ndarray) -> None:
        """One raw acquisition; a ``background`` entry in ``acquisition`` goes to its own channel."""
        meta = {k: v for k, v in acquisition.items() if k not in ("frames", "background")}
        stamp = stamp_ns_of(meta)
        background = acquisition.get("background")
        if background is not None and (
            self._background is None
            or self._since_background >= BACKGROUND_EVERY
            or self._chunks_written() != self._background_chunk
            or not np.array_equal(background, self._background)
        ):
            self._background = np.array(background, copy=True)
            self._since_background = 0
            data = _dumps({"frames": _samples(self._background)})
            self._background_crc = zlib.crc32(data)
            self._add(BACKGROUND_TOPIC, data, stamp)
            self._background_chunk = self._chunks_written()
        if background is not None:
            # which background applies, by content: replay finds it even when the message
            # written just before was lost to damage (an identical earlier one serves)
            meta["background_crc"] = self._background_crc
            self._since_background += 1
        synced = meta.get("stamp_host_ns")
        synced_ns = int(synced) if isinstance(synced, (int, np.integer)) and synced > 0 else 0
        self._add(
            ACQUISITION_TOPIC, {**meta, "frames": _samples(np.asarray(frames))}, stamp, synced_ns
        )
        self.counts["acquisitions"] += 1

    def _chunks_written(self) -> int:
        """Chunks the writer has finished: a new one starts with the background again, so a
        damaged chunk costs only its own acquisitions (the mcap Writer does not expose this
        count; without it the background is still repeated every BACKGROUND_EVERY)."""
        stats = getattr(self._writer, "_Writer__statistics", None)
        return getattr(stats, "chunk_count", 0)

    def write(self, record: dict) -> None:
        synced = record.get("stamp_host")  # the board's time on the host clock (protocol 2)
        log_ns = int(synced * 1e9) if isinstance(synced, float) and synced > 0 else 0
        self._add(POSITION_TOPIC, record, stamp_ns_of(record), log_ns)
        self.counts["records"] += 1

    def _add(self, topic: str, payload: dict | bytes, stamp: int, synced_ns: int = 0) -> None:
        """``synced_ns``: the acquisition's board time on the host clock, the log time when
        known (a live board speaking protocol 2), else the time of writing."""
        if self.closed:
            raise ValueError(f"{self.path}: recording already closed")
        data = payload if isinstance(payload, bytes) else _dumps(payload)
        now = stamp if self.log_time_from_stamp and stamp else (synced_ns or time.time_ns())
        with self._lock:  # close() may run in the signal watchdog meanwhile
            if self.closed:
                raise ValueError(f"{self.path}: recording already closed")
            self._writer.add_message(
                self._channels[topic],
                log_time=now,
                data=data,
                publish_time=stamp or now,
                sequence=self._sequence,
            )
        self._sequence += 1

    def close(self) -> None:
        """Write the summary and close the file; safe to call more than once, from any thread."""
        with self._lock:
            self._close()

    def _close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
        finally:
            self._fh.close()
        log.info(
            "recording %s finalized: %d acquisitions, %d records",
            self.path,
            self.counts["acquisitions"],
            self.counts["records"],
        )

    def __enter__(self) -> McapSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def stamp_ns_of(meta: dict) -> int:
    value = meta.get("timestamp_ns")
    return int(value) if isinstance(value, (int, np.integer)) and value > 0 else 0


def _samples(frames: np.ndarray) -> list:
    """Integers when the samples are integral (they are raw counts), None for non-finite."""
    if np.issubdtype(frames.dtype, np.integer):
        return frames.tolist()
    finite = np.isfinite(frames)
    if finite.all():
        return (
            frames.astype(np.int64).tolist()
            if np.array_equal(frames, np.round(frames))
            else frames.tolist()
        )
    return np.where(finite, frames, None).tolist()


def json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (bytes, bytearray)):
        return obj.hex()
    raise TypeError(f"{type(obj).__name__} is not JSON serializable")


def _dumps(payload: dict) -> bytes:
    return json.dumps(
        payload, separators=(",", ":"), allow_nan=False, default=json_default
    ).encode()
