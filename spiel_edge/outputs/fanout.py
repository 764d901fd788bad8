"""Several outputs at once: :class:`MultiSink`, and :func:`open_outputs`, which builds the one
the command-line options ask for (each output a :class:`~spiel_edge.outputs.sink.Sink`)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from spiel_edge.errors import ConfigError, OutputError
from spiel_edge.outputs.sink import Sink

log = logging.getLogger(__name__)


class MultiSink(Sink):
    """Fan records out to several sinks; a failing sink is logged and dropped, not fatal,
    until none is left (OutputError). ``failed`` names the dropped ones (the command's exit
    status says some output failed). The reader of stdout going away (BrokenPipeError) is
    passed on: it is a normal end, not a failure."""

    def __init__(self, sinks: list[Sink]):
        self.sinks = list(sinks)
        self.failed: list[str] = []

    @property
    def alive(self) -> bool:
        return bool(self.sinks)

    @property
    def capabilities(self) -> frozenset[str]:  # what one of its sinks can do
        return frozenset().union(*(sink.capabilities for sink in self.sinks))

    def parts(self) -> list[Sink]:
        return list(self.sinks)

    def write(self, record: dict) -> None:
        for sink in list(self.sinks):
            try:
                sink.write(record)
            except OSError as exc:
                self._drop(sink, exc)

    def set_status_provider(self, provider) -> None:
        """Give the ROS 2 sinks the session's state for /diagnostics (a callable -> dict)."""
        for sink in self.sinks:
            sink.set_status_provider(provider)

    def batch(self) -> None:
        """Sinks that can hold their writes (NDJSON) stop flushing each record; the caller
        calls :meth:`flush` when it has caught up with its input (a live run: no acquisition
        waiting), so a burst costs one flush, and a record never waits for a later one."""
        for sink in self.sinks:
            sink.batch()

    def flush(self) -> None:
        for sink in list(self.sinks):
            if not sink.hold:
                continue  # not held: flushed by its own write (MCAP keeps its chunking)
            try:
                sink.flush()
            except OSError as exc:
                self._drop(sink, exc)

    def write_acquisition(self, acquisition: dict, frames: np.ndarray) -> None:
        for sink in list(self.sinks):
            if not sink.wants_acquisitions:
                continue
            try:
                sink.write_acquisition(acquisition, frames)
            except OSError as exc:  # disk full, ...: stop recording, keep publishing
                self._drop(sink, exc)

    def _drop(self, sink: Sink, exc: OSError) -> None:
        if isinstance(exc, BrokenPipeError) and not sink.owns_file:
            raise exc
        name = type(sink).__name__
        log.error("output %s failed, dropping it: %s", name, exc)
        self.sinks.remove(sink)
        self.failed.append(f"{name}: {exc.strerror or exc}")
        _close_quietly(sink)
        if not self.sinks:
            raise OutputError(f"every output failed ({'; '.join(self.failed)})") from exc

    def close_files(self) -> None:
        """Finalize the outputs that are files (recordings, NDJSON files); nothing that could
        block on a reader. Safe to call again, and from the signal watchdog."""
        for sink in list(self.sinks):
            if sink.owns_file:
                try:
                    sink.close()
                except OSError as exc:
                    log.error("closing output %s failed: %s", type(sink).__name__, exc)
                    self.failed.append(f"{type(sink).__name__}: {exc.strerror or exc}")
                    self.sinks.remove(sink)

    def close(self) -> None:
        for sink in list(self.sinks):
            try:
                sink.close()
            except OSError as exc:
                log.error("closing output %s failed: %s", type(sink).__name__, exc)

    def __enter__(self) -> MultiSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _close_quietly(sink: Sink) -> None:
    try:
        sink.close()
    except Exception as exc:  # already failing; the first error was logged
        log.debug("closing %s: %s", type(sink).__name__, exc)


def recording_path(template: str | Path, now: float | None = None) -> Path:
    """Expand strftime fields (``spiel-%Y%m%d-%H%M%S.mcap``) so a restarted service never
    overwrites the recording of the run before."""
    text = str(template)
    if "%" in text:
        text = time.strftime(text, time.localtime(now))
    path = Path(text)
    if path.suffix != ".mcap":
        raise ConfigError(f"--record {template}: the file name must end in .mcap")
    if not path.parent.is_dir():
        raise ConfigError(f"--record {template}: folder {path.parent} does not exist")
    return path


def check_outputs(plan, output: str | None, record: str | Path | None) -> Path | None:
    """Check the file outputs of ``run`` before it starts (io.guard rules); the recording's
    expanded path, to pass to :func:`open_outputs`."""
    plan.output(output, "--output")
    if record is None:
        return None
    path = recording_path(record)
    plan.output(path, "--record")
    return path


@dataclass(frozen=True)
class SinkOptions:
    """What the sinks of one command share (open_outputs' keyword options)."""

    metadata: dict[str, Any] | None = None
    receivers_mm: Any = None
    exclusive: bool = False  # no --force: never replace a file
    record_profile: str = "json"
    zenoh_encoding: str = "json"
    ros2: Any = None
    zenoh_settings: Any = None


def _ndjson_sink(target: str, o: SinkOptions) -> Sink:
    from spiel_edge.outputs.ndjson import NdjsonSink

    return NdjsonSink(target, exclusive=o.exclusive)


# every output a command can ask for, by its option, in the order they are opened
SINKS: tuple[tuple[str, Callable[[Any, SinkOptions], Sink]], ...] = (
    ("output", _ndjson_sink),
    ("record", lambda path, o: _mcap_sink(path, o.metadata, o.record_profile, o.ros2, o.exclusive)),
    ("udp", lambda target, o: _udp_sink(target)),
    ("foxglove", lambda bind, o: _foxglove_sink(bind, o.receivers_mm, o.ros2)),
    ("zenoh", lambda key, o: _zenoh_sink(key, o.zenoh_encoding, o.ros2, o.zenoh_settings)),
)


def open_outputs(
    output: str | None = "-",
    record: str | Path | None = None,
    udp: Sequence[str] | str | None = None,
    foxglove: str | None = None,
    zenoh: str | None = None,
    *,
    metadata: dict[str, Any] | None = None,
    receivers_mm: Any = None,
    force: bool = True,
    record_profile: str = "json",
    zenoh_encoding: str = "json",
    ros2: Any = None,
    zenoh_settings: Any = None,
) -> MultiSink:
    """The sinks the options ask for, all at once: NDJSON (``output``; None for none), an MCAP
    recording, UDP targets, a Foxglove live view, Zenoh. Closes what it opened on failure.

    ``record_profile`` "ros2" and ``zenoh_encoding`` "cdr" write ROS 2 messages in CDR with the
    frame id and static transforms of ``ros2`` (outputs.ros2.Ros2Settings)."""
    options = SinkOptions(
        metadata, receivers_mm, not force, record_profile, zenoh_encoding, ros2, zenoh_settings
    )
    values = {  # option -> the sinks it asks for (--udp may name several targets)
        "output": [] if output is None else [output],
        "record": [] if record is None else [recording_path(record)],
        "udp": [udp] if isinstance(udp, str) else list(udp or []),
        "foxglove": [] if foxglove is None else [foxglove],
        "zenoh": [] if zenoh is None else [zenoh],
    }
    factories = [
        partial(make, value, options) for option, make in SINKS for value in values[option]
    ]
    sinks: list[Sink] = []
    try:
        for make in factories:
            sinks.append(make())
    except BaseException:
        for sink in sinks:
            _close_quietly(sink)
        raise
    return MultiSink(sinks)


def check_output_key(key: str, encoding: str) -> None:
    """``--zenoh KEY`` checked before any board is opened (ConfigError): a concrete key, and
    for the ROS 2 encodings a prefix of valid ROS 2 topics."""
    if encoding in ("rmw_zenoh", "cdr"):
        from spiel_edge.outputs.rmw_zenoh.sink import topics_of

        topics_of(key)
    from spiel_edge.outputs.zenoh import publish_key_problem

    if problem := publish_key_problem(key.strip("/") if encoding != "json" else key):
        raise ConfigError(f"--zenoh {key!r} {problem}")


def _mcap_sink(
    path: Path,
    metadata: dict[str, Any] | None,
    profile: str = "json",
    ros2: Any = None,
    exclusive: bool = False,
) -> Sink:
    from spiel_edge.recordings.mcap_writer import McapSink

    try:
        if profile == "ros2":
            from spiel_edge.outputs.ros2 import Ros2Settings
            from spiel_edge.recordings.ros2_mcap import Ros2McapSink

            ros2 = ros2 or Ros2Settings()
            return Ros2McapSink(path, ros2=ros2, metadata=metadata, exclusive=exclusive)
        return McapSink(path, metadata=metadata, exclusive=exclusive)
    except ConfigError as exc:
        raise ConfigError(f"--record {exc}") from exc
    except OSError as exc:
        raise ConfigError(f"--record {path}: cannot write: {exc.strerror or exc}") from exc


def _udp_sink(target: str) -> Sink:
    from spiel_edge.outputs.udp import UdpSink

    return UdpSink(target)


def _foxglove_sink(bind: str, receivers_mm: Any, ros2: Any = None) -> Sink:
    from spiel_edge.outputs.foxglove import FoxgloveSink

    return FoxgloveSink(bind, receivers_mm=receivers_mm, ros2=ros2)


def _zenoh_sink(key: str, encoding: str = "json", ros2: Any = None, settings: Any = None) -> Sink:
    if encoding == "rmw_zenoh":
        from spiel_edge.outputs.rmw_zenoh.sink import RmwZenohSink

        return RmwZenohSink(key, ros2, settings)
    if encoding == "cdr":
        from spiel_edge.outputs.zenoh_ros2 import ZenohRos2Sink

        return ZenohRos2Sink(key, ros2, settings=settings)
    from spiel_edge.outputs.zenoh import ZenohSink

    return ZenohSink(key, settings=settings)
