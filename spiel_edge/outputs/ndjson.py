"""NDJSON records to stdout or a file: one JSON object per line, flushed per record."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TextIO


class NdjsonSink:
    def __init__(self, target: str | Path = "-"):
        self._own = str(target) != "-"
        self._fh: TextIO = open(target, "w", encoding="utf-8") if self._own else sys.stdout  # noqa: SIM115

    def write(self, record: dict) -> None:
        self._fh.write(json.dumps(record, separators=(",", ":"), allow_nan=False) + "\n")
        self._fh.flush()

    def close(self) -> None:
        if self._own:
            self._fh.close()
        else:
            self._fh.flush()
