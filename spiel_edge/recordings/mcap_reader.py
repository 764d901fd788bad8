"""Reading MCAP recordings written by :class:`spiel_edge.recordings.mcap_writer.McapSink`: every recorded
acquisition with the background in force, a damaged, cut or unfinalized file read as far as
it goes (:mod:`spiel_edge.recordings.mcap_scan`), one error entry at the end saying what was skipped.

Inputs are bounded before they are parsed: a message larger than the profile's frame allows
is skipped unread, and a hostile JSON payload (deep nesting, huge numbers) becomes an error
for that message only.
"""

from __future__ import annotations

import json
import logging
import os
import stat
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.messages.cdr import ENCAPSULATION, decode_acquisition
from spiel_edge.recordings.mcap_scan import (
    MAGIC,
    OP_HEADER,
    OP_METADATA,
    RECORD_HEAD,
    Limits,
    McapScanner,
    RawMessage,
)
from spiel_edge.recordings.spiel_csv import Recording
from spiel_edge.safety.guard import shorten
from spiel_edge.safety.limits import InputLimits

log = logging.getLogger(__name__)

ACQUISITION_TOPIC = "/spiel/acquisition"
BACKGROUND_TOPIC = "/spiel/background"
POSITION_TOPIC = "/spiel/position"
METADATA_NAME = "spiel-edge"  # the metadata record McapSink writes (recordings/mcap_writer.py)
METADATA_HEAD_BYTES = 64 * 1024  # header and metadata records are read from this much
KEEP_BACKGROUNDS = 8  # distinct backgrounds remembered, by the CRC-32 of their message


def iter_mcap_recordings(
    path: str | Path, limits: InputLimits | None = None, report: list | None = None
) -> Iterator[Recording]:
    """Each recorded acquisition with its background; bad messages become error entries.

    A damaged, cut or unfinalized file is read as far as it goes; then one error entry says
    what was skipped (``report``, when given, receives the :class:`ScanReport`)."""
    limits = limits or InputLimits()
    path = Path(path)
    with open_recording(path) as (fh, size):
        scanner = McapScanner(fh, size, scan_limits(limits))
        count = 0
        for rec in _recordings(scanner, path.name, limits):
            count += 1
            yield rec
        if report is not None:
            report.append(scanner.report)
        scan = scanner.report
        if scan.damaged or scan.truncated or not scan.finalized:
            how = "ends early" if scan.truncated or not scan.finalized else "is damaged"
            message = f"{path.name}: recording {how} after {count} acquisitions: {scan.summary()}"
            log.warning("%s", message)
            yield Recording(f"{path.name}#end", None, None, message)


class open_recording:  # noqa: N801 - used as a context manager
    """A regular MCAP file opened for reading: (file, size); InputError otherwise."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self):
        try:
            fd = os.open(self.path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        except OSError as exc:
            raise InputError(
                f"{shorten(self.path)}: cannot open recording: {exc.strerror}"
            ) from exc
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            os.close(fd)
            raise InputError(f"{shorten(self.path)}: not a regular file")
        self.fh = os.fdopen(fd, "rb")
        if self.fh.read(len(MAGIC)) != MAGIC:
            self.fh.close()
            raise InputError(f"{shorten(self.path)}: not an MCAP file")
        return self.fh, st.st_size

    def __exit__(self, *exc: object) -> None:
        self.fh.close()


def recording_metadata(path: str | Path) -> dict[str, str]:
    """The ``spiel-edge`` metadata record that McapSink writes right after the header (``port``,
    ``profile``, ...); {} when the file has none or its head is unreadable."""
    try:
        with open_recording(Path(path)) as (fh, _size):
            head = fh.read(METADATA_HEAD_BYTES)
    except InputError:
        return {}
    pos = 0
    while pos + RECORD_HEAD.size <= len(head):
        op, length = RECORD_HEAD.unpack_from(head, pos)
        body = head[pos + RECORD_HEAD.size : pos + RECORD_HEAD.size + length]
        if op == OP_METADATA and len(body) == length:
            name, entries = _metadata(body)
            if name == METADATA_NAME:
                return entries
        elif op != OP_HEADER:
            break  # the metadata comes before the first chunk
        pos += RECORD_HEAD.size + length
    return {}


def _metadata(body: bytes) -> tuple[str, dict[str, str]]:
    """A Metadata record's body: name, then a map of string pairs ("", {} when malformed)."""
    try:
        name, pos = _string(body, 0)
        (size,) = struct.unpack_from("<I", body, pos)
        end, pos = pos + 4 + size, pos + 4
        entries = {}
        while pos < end:
            key, pos = _string(body, pos)
            entries[key], pos = _string(body, pos)
        return name, entries
    except (struct.error, UnicodeDecodeError, ValueError):
        return "", {}


def _string(data: bytes, pos: int) -> tuple[str, int]:
    (size,) = struct.unpack_from("<I", data, pos)
    if pos + 4 + size > len(data):
        raise ValueError("string runs past its record")
    return data[pos + 4 : pos + 4 + size].decode(), pos + 4 + size


def scan_limits(limits: InputLimits) -> Limits:
    """Message and chunk bounds from the profile's frame size (memory stays about that)."""
    message = limits.max_json_bytes
    return Limits(max_message=message, max_chunk=max(4 << 20, 4 * message))


def topic_of(msg: RawMessage) -> str:
    """The channel's topic; when the channel record was lost, told by the payload's keys."""
    if msg.topic is not None:
        return msg.topic
    head = msg.data[:4096]
    if b'"position_mm"' in head or b'"reason"' in head:
        return POSITION_TOPIC
    if msg.data.startswith(b'{"frames"') and msg.data.rstrip().endswith(b"]]}"):
        return BACKGROUND_TOPIC
    return ACQUISITION_TOPIC


def _recordings(scanner: McapScanner, name: str, limits: InputLimits) -> Iterator[Recording]:
    backgrounds: dict[int, np.ndarray | str] = {}
    current: np.ndarray | str | None = None  # str: why the last background is unreadable
    for msg in scanner.messages():
        topic = topic_of(msg)
        if topic == BACKGROUND_TOPIC:
            current = _background_of(msg, limits)
            backgrounds[zlib.crc32(msg.data)] = current
            while len(backgrounds) > KEEP_BACKGROUNDS:
                backgrounds.pop(next(iter(backgrounds)))
        elif topic == ACQUISITION_TOPIC:
            yield _recording(name, msg, current, backgrounds, limits)


def load_payload(data: bytes) -> dict:
    """A JSON object; ValueError for anything else (deep nesting and huge numbers included).

    A CDR message (a ``--record-profile ros2`` recording: spiel_msgs/msg/Acquisition) reads as
    the same {"seq", "frames"} object."""
    if data[:4] == ENCAPSULATION:
        seq, frames = decode_acquisition(data)
        return {"seq": seq, "frames": frames.tolist()}
    try:
        payload = json.loads(data)
    except RecursionError as exc:
        raise ValueError("JSON nested too deeply") from exc
    except (UnicodeDecodeError, MemoryError) as exc:
        raise ValueError(type(exc).__name__) from exc
    if not isinstance(payload, dict):
        raise ValueError(f"expected a JSON object, got {type(payload).__name__}")
    return payload


def _background_of(msg: RawMessage, limits: InputLimits) -> np.ndarray | str:
    try:
        return frames_of(load_payload(msg.data), limits)
    except (ValueError, TypeError, KeyError, OverflowError) as exc:
        return f"background message {msg.sequence} is unreadable: {shorten(exc)}"


def _recording(
    name: str,
    msg: RawMessage,
    current: np.ndarray | str | None,
    backgrounds: dict[int, np.ndarray | str],
    limits: InputLimits,
) -> Recording:
    source = f"{name}#{msg.sequence}"
    try:
        payload = load_payload(msg.data)
        seq = payload.get("seq", msg.sequence)
        source = f"{name}#{seq if isinstance(seq, int) and 0 <= seq < 1 << 63 else msg.sequence}"
        frames = frames_of(payload, limits)
    except (ValueError, TypeError, KeyError, OverflowError) as exc:
        return Recording(source, None, None, f"{source}: bad acquisition message: {shorten(exc)}")
    background = current
    wanted = payload.get("background_crc")
    if isinstance(wanted, int):  # written since the background is repeated: find that one
        background = backgrounds.get(wanted, f"its background (CRC {wanted:#010x}) was lost")
    if isinstance(background, str):
        return Recording(source, None, None, f"{source}: {background}")
    if not np.all(np.isfinite(frames)):
        return Recording(
            source, None, None, f"{source}: frames contain missing or non-finite samples"
        )
    if background is not None and background.shape != frames.shape:
        return Recording(
            source,
            None,
            None,
            f"{source}: background shape {background.shape} differs from frames {frames.shape}",
        )
    stamp = msg.publish_time  # the acquisition's host time, as McapSink writes it
    return Recording(
        source,
        frames,
        background,
        time_s=stamp / 1e9 if stamp > 0 else None,
        truth_mm=_truth_of(payload),
    )


def _truth_of(payload: dict) -> np.ndarray | None:
    """The ground truth the acquisition was recorded with (a virtual board's), when valid."""
    truth = payload.get("truth_mm")
    if not (isinstance(truth, list) and len(truth) == 3):
        return None
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in truth):
        return None
    arr = np.array(truth, dtype=np.float64)
    return arr if np.isfinite(arr).all() else None


def frames_of(payload: dict, limits: InputLimits | None = None) -> np.ndarray:
    rows = payload["frames"]
    if not isinstance(rows, list) or not all(isinstance(r, list) for r in rows):
        raise ValueError("frames must be a list of channels, each a list of samples")
    if limits is not None:
        limits.check_shape(len(rows), max((len(r) for r in rows), default=0))
    frames = np.array(rows, dtype=np.float64)  # None -> nan; ragged -> ValueError
    if frames.ndim != 2:
        raise ValueError(f"frames must be channels x samples, got shape {frames.shape}")
    return frames
