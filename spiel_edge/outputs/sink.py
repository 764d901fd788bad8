"""What every output is: a Sink, with every hook the fan-out and the live loop call.

A Sink takes JSON-ready record dicts (the README's record schema) and must be closed. The
hooks below are no-ops unless a sink overrides them: recordings keep the raw acquisitions
(``write_acquisition``, asked for only when ``wants_acquisitions``) and own a file that a
signal must finalize (``owns_file``); a sink that can hold its writes until the live loop has caught up
(``hold``) pushes them out in ``flush``.
"""

from __future__ import annotations

import numpy as np


class Sink:
    owns_file: bool = False  # a file this sink writes and finalizes (closed first on a signal)
    wants_acquisitions: bool = False  # write_acquisition does something
    hold: bool = False  # True: write() leaves flushing to flush() (set by MultiSink.batch)

    def write(self, record: dict) -> None:
        """One record."""

    def write_acquisition(self, acquisition: dict, frames: np.ndarray) -> None:
        """The raw samples of one acquisition and what was used with them (``background``,
        ``seq``, times): recordings keep them; nothing otherwise."""

    def set_status_provider(self, provider) -> None:
        """The session's state for /diagnostics (a callable -> dict): ROS 2 sinks use it."""

    def flush(self) -> None:
        """Push held writes out (a sink that holds them: NDJSON); nothing otherwise."""

    @property
    def alive(self) -> bool:
        """False once the sink can take nothing more (a fan-out whose outputs all failed)."""
        return True

    def close(self) -> None:
        """Finalize and release; safe to call again."""
