"""A status line redrawn in place on a terminal's stderr, that log lines never join.

``run`` redraws its status with ``\\r`` and no newline; a log record written meanwhile would
start on that line ("... 12 fixes 2026-12-03 WARNING ..."). While the line is shown, a filter
on the root log handler clears it before the record is written; the next status redraws it.
"""

from __future__ import annotations

import logging
import sys

import click


class StatusLine:
    def __init__(self) -> None:
        self.shown = False
        self._handlers: list[logging.Handler] = []

    def show(self, text: str) -> None:
        if not self._handlers:
            self._handlers = list(logging.getLogger().handlers)
            for handler in self._handlers:
                handler.addFilter(self._before_log)
        click.echo("\r" + text + "\x1b[K", err=True, nl=False)
        self.shown = True

    def clear(self) -> None:
        if self.shown:
            self.shown = False
            try:
                # a terminal: erase the line; a file (--status into a log): end it
                sys.stderr.write("\r\x1b[K" if sys.stderr.isatty() else "\n")
                sys.stderr.flush()
            except (OSError, ValueError):
                pass

    def close(self) -> None:
        """End the line (the summary goes below it) and stop watching the log."""
        if self.shown:
            click.echo("", err=True)
            self.shown = False
        for handler in self._handlers:
            handler.removeFilter(self._before_log)
        self._handlers = []

    def _before_log(self, record: logging.LogRecord) -> bool:
        self.clear()
        return True


def say_live_views(sink) -> None:
    """Where to look, said at start without -v: the Foxglove server's address and layout
    (`run`, `run --robot`, `fuse`)."""
    for out in sink.parts():
        if out.view_line:
            click.echo(f"{out.view_line} (layout: packaging/foxglove/spiel-edge.json)", err=True)
