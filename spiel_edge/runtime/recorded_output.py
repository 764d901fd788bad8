"""Where `spiel-edge replay` writes: NDJSON (a file or stdout), or an MCAP recording
(``-o FILE.mcap``) laid out as `run --record` writes it, so it replays again.

The MCAP holds, per replayed acquisition, its raw frames and background and its record (the
JSON profile), or with ``--record-profile ros2`` the ROS 2 messages of recordings/ros2_mcap.py
and the static transforms on ``/tf_static``. Records gain ``seq`` and ``host_time``: the
acquisition's capture time when the input recording has it (an MCAP), else the replay's start
time plus NOMINAL_PERIOD_S per acquisition.

The file rules of safety/guard.py hold: the recording is written to a temporary file beside the
target and moved into place only once finalized (:meth:`ReplayMcap.close`, also run by the
signal watchdog), without ``--force`` by an exclusive link that never replaces a file that
appeared meanwhile; a failure leaves the target as it was.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from spiel_edge.errors import ConfigError
from spiel_edge.outputs.ndjson import NdjsonSink
from spiel_edge.runtime.recorded import Replayed
from spiel_edge.runtime.track_records import NOMINAL_PERIOD_S
from spiel_edge.safety.guard import current_umask, publish, shorten

log = logging.getLogger(__name__)

MCAP_SUFFIX = ".mcap"


def is_mcap_output(output: str | None) -> bool:
    return output is not None and str(output).lower().endswith(MCAP_SUFFIX)


class ReplayNdjson:
    """One NDJSON record per replayed acquisition (atomic when it is a file)."""

    def __init__(self, output: str) -> None:
        self.sink = NdjsonSink(output, atomic=True)
        self.owns_file = self.sink.owns_file

    def write(self, item: Replayed) -> None:
        self.sink.write(item.record())

    def close(self) -> None:
        self.sink.close()

    def discard(self) -> None:
        self.sink.discard()


class ReplayClock:
    """Each acquisition's time: its recorded capture time, else one nominal period on."""

    def __init__(self, start_s: float | None = None) -> None:
        self.start_s = time.time() if start_s is None else start_s
        self.last_s: float | None = None

    def time_of(self, item: Replayed) -> float:
        recorded = item.recording.time_s if item.recording is not None else None
        if recorded is not None:
            t = recorded
        else:
            t = self.start_s if self.last_s is None else self.last_s + NOMINAL_PERIOD_S
        self.last_s = t
        return t


class ReplayMcap:
    """An MCAP recording of a replay, moved into place when finalized."""

    def __init__(
        self,
        path: str | Path,
        *,
        force: bool,
        record_profile: str = "json",
        ros2: Any = None,
        metadata: dict[str, Any] | None = None,
    ) -> None:
        self.path = Path(path)
        self.force = force
        self.owns_file = True
        self.clock = ReplayClock()
        self.count = 0
        self._lock = threading.Lock()
        self._done = False
        special = self.path.exists() and not self.path.is_file()  # /dev/null: written as is
        self._tmp: Path | None = None if special else _temporary_beside(self.path)
        try:
            self.sink = _mcap_sink(self._tmp or self.path, metadata, record_profile, ros2)
        except BaseException:
            self._remove_temporary()
            raise
        self.sink.log_time_from_stamp = True
        self._ros2 = record_profile == "ros2"

    def write(self, item: Replayed) -> None:
        t = self.clock.time_of(item)
        self._write_transforms(t)
        record = {"seq": self.count, "host_time": round(t, 6), **item.record()}
        rec = item.recording
        if rec is not None and rec.frames is not None:
            meta = {"seq": self.count, "timestamp_ns": int(t * 1e9), "source": rec.source}
            if rec.truth_mm is not None:
                meta["truth_mm"] = [round(float(v), 2) for v in rec.truth_mm]
            self.sink.write_acquisition({**meta, "background": rec.background}, rec.frames)
        self.sink.write(record)
        self.count += 1

    def _write_transforms(self, t: float) -> None:
        """/tf_static once, before the first acquisition and stamped with its time."""
        if self._ros2:
            self.sink.write_transforms(t)  # the sink writes them once

    def close(self) -> None:
        """Finalize the recording and move it into place (once; also from the watchdog)."""
        with self._lock:
            if self._done:
                return
            self._done = True
            try:
                self._write_transforms(self.clock.start_s)  # an empty replay has them too
                self.sink.close()
                if self._tmp is not None:
                    _publish(self._tmp, self.path, self.force)
            finally:
                self._remove_temporary()

    def discard(self) -> None:
        """Drop the recording; the target stays as it was."""
        with self._lock:
            if self._done:
                return
            self._done = True
            with contextlib.suppress(Exception):
                self.sink.close()
            self._remove_temporary()

    def _remove_temporary(self) -> None:
        if self._tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(self._tmp)


def _mcap_sink(path: Path, metadata: dict | None, record_profile: str, ros2: Any):
    """The recording sink, writing ``path`` (the mcap package is imported only when asked);
    the static transforms are written with the first acquisition, at its time."""
    if record_profile == "ros2":
        from spiel_edge.outputs.ros2 import Ros2Settings
        from spiel_edge.recordings.ros2_mcap import Ros2McapSink

        return Ros2McapSink(
            path, ros2=ros2 or Ros2Settings(), metadata=metadata, transforms_now=False
        )
    from spiel_edge.recordings.mcap_writer import McapSink

    return McapSink(path, metadata=metadata)


def _temporary_beside(path: Path) -> Path:
    fd, name = tempfile.mkstemp(prefix=f".{path.name[:40]}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    return Path(name)


def _publish(tmp: Path, path: Path, force: bool) -> None:
    """``tmp`` synced and moved to ``path``: replacing it with ``force``, else only when
    ``path`` still does not exist (checked atomically by the link)."""
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.chmod(tmp, 0o666 & ~current_umask())
    publish(tmp, path, "the replay", force=force)


def open_replay_output(
    output: str,
    *,
    force: bool,
    record_profile: str = "json",
    ros2: Any = None,
    metadata: dict[str, Any] | None = None,
) -> ReplayNdjson | ReplayMcap:
    """The output `replay -o` asks for (its path already checked by the command's FilePlan)."""
    if not is_mcap_output(output):
        if record_profile != "json":
            raise ConfigError(
                f"--record-profile {record_profile}: needs an MCAP output (-o FILE.mcap)"
            )
        return ReplayNdjson(output)
    try:
        return ReplayMcap(
            output, force=force, record_profile=record_profile, ros2=ros2, metadata=metadata
        )
    except ConfigError as exc:
        raise ConfigError(f"--output {exc}") from exc
    except OSError as exc:
        raise ConfigError(f"--output {shorten(output)}: cannot write: {exc.strerror}") from exc
