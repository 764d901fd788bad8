"""Reading MCAP recordings written by :class:`spiel_edge.outputs.mcap.McapSink`: every recorded
acquisition with the background in force, a damaged or unfinalized file read as far as it goes."""

from __future__ import annotations

import json
import logging
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, SeekingReader

from spiel_edge.errors import InputError
from spiel_edge.io.spiel_csv import Recording

log = logging.getLogger(__name__)

ACQUISITION_TOPIC = "/spiel/acquisition"
BACKGROUND_TOPIC = "/spiel/background"
POSITION_TOPIC = "/spiel/position"


def iter_mcap_recordings(path: str | Path) -> Iterator[Recording]:
    """Each recorded acquisition with the background in force; bad messages become errors.

    A file that was never finalized is read up to where it ends, then one error entry says so.
    """
    path = Path(path)
    try:
        fh = open(path, "rb")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise InputError(f"{path}: cannot open recording: {exc}") from exc
    with fh:
        yield from _recordings(fh, path)


def _recordings(fh: IO[bytes], path: str | Path) -> Iterator[Recording]:
    path = Path(path)
    if fh.read(8) != b"\x89MCAP0\r\n":
        raise InputError(f"{path}: not an MCAP file")
    fh.seek(0)
    background: np.ndarray | str | None = None  # str: why the last background is unreadable
    count = 0
    try:
        for topic, data, sequence in _messages(fh):
            if topic == BACKGROUND_TOPIC:
                background = _background_of(data, sequence)
                continue
            count += 1
            yield _recording(path.name, data, sequence, background)
    except (
        McapError,
        ValueError,
        EOFError,
        OSError,
        struct.error,
    ) as exc:  # truncated or corrupt tail
        message = f"{path.name}: recording ends early after {count} acquisitions ({type(exc).__name__}: {exc})"
        log.warning("%s", message)
        yield Recording(f"{path.name}#end", None, None, message)


def _messages(fh: IO[bytes]) -> Iterator[tuple[str, bytes, int]]:
    """(topic, data, sequence) in file order; the index when the file is finalized, else a scan."""
    topics = [ACQUISITION_TOPIC, BACKGROUND_TOPIC]
    try:
        reader = SeekingReader(fh)
        reader.get_summary()  # raises on a file without footer/summary
    except (McapError, ValueError, EOFError, OSError, struct.error):
        fh.seek(0)
        reader = NonSeekingReader(fh)
    for _schema, channel, message in reader.iter_messages(topics=topics, log_time_order=False):
        yield channel.topic, message.data, message.sequence


def _background_of(data: bytes, sequence: int) -> np.ndarray | str:
    try:
        return _frames_of(json.loads(data))
    except (ValueError, TypeError, KeyError) as exc:
        return f"background message {sequence} is unreadable: {exc!r}"


def _recording(
    name: str, data: bytes, sequence: int, background: np.ndarray | str | None
) -> Recording:
    source = f"{name}#{sequence}"
    try:
        payload = json.loads(data)
        source = f"{name}#{payload.get('seq', sequence)}"
        frames = _frames_of(payload)
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        return Recording(source, None, None, f"{source}: bad acquisition message: {exc!r}")
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
    return Recording(source, frames, background)


def _frames_of(payload: dict) -> np.ndarray:
    if not isinstance(payload, dict):
        raise TypeError(f"expected a JSON object, got {type(payload).__name__}")
    frames = np.array(payload["frames"], dtype=np.float64)  # None -> nan; ragged -> ValueError
    if frames.ndim != 2:
        raise ValueError(f"frames must be channels x samples, got shape {frames.shape}")
    return frames
