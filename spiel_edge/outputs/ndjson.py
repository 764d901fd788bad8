"""NDJSON records to stdout or a file: one JSON object per line, flushed per record (or,
held by a live run, whenever it has caught up: ``MultiSink.batch``)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TextIO

from spiel_edge.outputs.sink import FILE, HOLD, Sink
from spiel_edge.safety.guard import AtomicTextFile, open_exclusive

# one encoder for every record (json.dumps with options builds one per call); same text
_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)


class NdjsonSink(Sink):
    """``exclusive``: the file must not exist yet (no --force); ``atomic``: written to a
    temporary file renamed into place on close (a failed or interrupted command leaves the
    target untouched, unless :meth:`commit` is called)."""

    def __init__(self, target: str | Path = "-", *, exclusive: bool = False, atomic: bool = False):
        self.capabilities = frozenset({HOLD, FILE} if str(target) != "-" else {HOLD})
        self._atomic: AtomicTextFile | None = None
        if not self.owns_file:
            self._fh: TextIO = sys.stdout
        elif atomic and not (Path(target).exists() and not Path(target).is_file()):
            self._atomic = AtomicTextFile(target)
            self._fh = self._atomic.fh
        elif exclusive:
            self._fh = open_exclusive(target, force=False, text=True)
        else:
            self._fh = open_exclusive(target, force=True, text=True)

    def write(self, record: dict) -> None:
        self._fh.write(_ENCODER.encode(record) + "\n")
        if not self.hold:
            self._fh.flush()

    def flush(self) -> None:
        self._fh.flush()

    def close(self) -> None:
        """Close the file (an atomic one is renamed into place); flush stdout."""
        if self._atomic is not None:
            self._atomic.commit()
        elif self.owns_file:
            self._fh.close()
        else:
            self._fh.flush()

    def discard(self) -> None:
        """An atomic file is dropped, leaving the target as it was."""
        if self._atomic is not None:
            self._atomic.discard()
        elif self.owns_file:
            self._fh.close()
