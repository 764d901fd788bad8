"""What every output is: a Sink, with named capabilities and every hook the fan-out and the
live loop call.

A Sink takes JSON-ready record dicts (the README's record schema) and must be closed (close
is safe to call again). What a sink can do beyond ``write`` is said by the names in its
``capabilities``, never probed; the hooks below are no-ops unless a sink overrides them:

- ``ACQUISITIONS``: ``write_acquisition`` keeps the raw samples (recordings, the echogram);
- ``FILE``: it writes a file that it finalizes on close (closed first on a signal);
- ``HOLD``: after ``batch()`` its writes wait for ``flush()`` (the live loop flushes once it
  has caught up: NDJSON);
- ``STATUS``: it publishes the session's state given by ``set_status_provider``
  (/diagnostics of the ROS 2 sinks);
- ``VIEW``: a live view whose address ``view_line`` is said at start (Foxglove).

A sink that sits below this package (recordings/mcap_writer.py) declares the same names as
plain strings. tests/headless/test_sink_contract.py holds every sink to this contract.
"""

from __future__ import annotations

import numpy as np

ACQUISITIONS = "acquisitions"
FILE = "file"
HOLD = "hold"
STATUS = "status"
VIEW = "view"
CAPABILITIES = frozenset({ACQUISITIONS, FILE, HOLD, STATUS, VIEW})


class Sink:
    capabilities: frozenset[str] = frozenset()
    hold: bool = False  # True: write() leaves flushing to flush() (set by batch())
    view_line: str = ""  # VIEW: where to look, said at start

    @property
    def owns_file(self) -> bool:
        """A file this sink writes and finalizes (closed first on a signal)."""
        return FILE in self.capabilities

    @property
    def wants_acquisitions(self) -> bool:
        """write_acquisition does something."""
        return ACQUISITIONS in self.capabilities

    def write(self, record: dict) -> None:
        """One record."""

    def write_acquisition(self, acquisition: dict, frames: np.ndarray) -> None:
        """The raw samples of one acquisition and what was used with them (``background``,
        ``seq``, times): recordings keep them; nothing otherwise."""

    def set_status_provider(self, provider) -> None:
        """The session's state for /diagnostics (a callable -> dict): ROS 2 sinks use it."""

    def batch(self) -> None:
        """HOLD: from now on writes wait for :meth:`flush`; nothing otherwise."""
        if HOLD in self.capabilities:
            self.hold = True

    def flush(self) -> None:
        """Push held writes out (a sink that holds them: NDJSON); nothing otherwise."""

    def parts(self) -> list[Sink]:
        """The outputs this sink is made of: itself (a fan-out: each of its sinks)."""
        return [self]

    @property
    def alive(self) -> bool:
        """False once the sink can take nothing more (a fan-out whose outputs all failed)."""
        return True

    def close(self) -> None:
        """Finalize and release; safe to call again."""
