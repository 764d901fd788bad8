"""Quoting for systemd unit files (systemd.service(5) "Command lines", systemd.unit(5)
"Specifiers"): a value that would change the meaning of the unit is escaped or refused."""

from __future__ import annotations

from spiel_edge.errors import ConfigError
from spiel_edge.safety.guard import shorten

_NEEDS_QUOTES = set(" \t\"'\\;")


def exec_path(path: str) -> str:
    """``path`` as the first word of ExecStart: absolute, no control characters (a newline
    would start a new directive), ``%`` doubled (specifiers), ``$`` doubled (variables),
    quoted when it holds spaces, quotes, backslashes or ``;``."""
    if not path.startswith("/"):
        raise ConfigError(f"--exec {shorten(path)!r}: must be an absolute path")
    bad = sorted({f"{ord(c):#04x}" for c in path if ord(c) < 0x20 or ord(c) == 0x7F})
    if bad:
        raise ConfigError(
            f"--exec {shorten(path)!r}: control characters ({', '.join(bad)}) cannot go in a unit"
        )
    text = path.replace("%", "%%").replace("$", "$$")
    if not _NEEDS_QUOTES & set(text):
        return text
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'
