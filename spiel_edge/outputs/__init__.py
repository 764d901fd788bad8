"""Where records go: one Sink per destination, several at once through MultiSink.

A Sink takes JSON-ready record dicts (see the README's record schema) and must be closed;
raw acquisitions go to sinks that want them (recordings) through ``write_acquisition``.
"""

from __future__ import annotations

import logging
from typing import Protocol

import numpy as np

log = logging.getLogger(__name__)


class Sink(Protocol):
    def write(self, record: dict) -> None: ...

    def close(self) -> None: ...


class MultiSink:
    """Fan records out to several sinks; a failing sink is logged and dropped, not fatal."""

    def __init__(self, sinks: list[Sink]):
        self.sinks = list(sinks)

    def write(self, record: dict) -> None:
        for sink in list(self.sinks):
            try:
                sink.write(record)
            except OSError as exc:
                log.error("output %s failed, dropping it: %s", type(sink).__name__, exc)
                self.sinks.remove(sink)

    def write_acquisition(self, acquisition: dict, frames: np.ndarray) -> None:
        for sink in self.sinks:
            hook = getattr(sink, "write_acquisition", None)
            if hook is not None:
                hook(acquisition, frames)

    def close(self) -> None:
        for sink in self.sinks:
            try:
                sink.close()
            except OSError as exc:
                log.error("closing output %s failed: %s", type(sink).__name__, exc)

    def __enter__(self) -> MultiSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
