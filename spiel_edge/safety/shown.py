"""What a message may show of user-supplied text (file names, tokens, a board's strings): escaped,
so nothing raw reaches a terminal, and short, so a 10 MB token is not echoed back."""

from __future__ import annotations

import re

MAX_SHOWN = 200  # characters of user-supplied text echoed into a message: a deep path whole,
# a 10 MB token not (80 cut the paths of a test run under pytest-xdist)


# control characters, lone surrogates (bytes that were not UTF-8), line and paragraph
# separators and the bidirectional overrides that make a name read differently than it is
_UNPRINTABLE = re.compile(
    r"[\x00-\x1f\x7f-\x9f\ud800-\udfff\u2028\u2029\u200e\u200f\u202a-\u202e\u2066-\u2069]"
)


def _escape_char(match: re.Match) -> str:
    char = match.group()
    code = ord(char)
    if 0xDC80 <= code <= 0xDCFF:  # a byte that was not UTF-8 (os.fsdecode's surrogateescape)
        return f"\\x{code - 0xDC00:02x}"
    return {"\n": "\\n", "\r": "\\r", "\t": "\\t"}.get(char) or (
        f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"
    )


def escape(text: object) -> str:
    """``text`` safe for one line of a terminal: control characters (a newline, an escape
    sequence from a board), bytes that were not UTF-8 in a file name and lone surrogates are
    shown as ``\\n``, ``\\x1b``, ``\\xff``."""
    text = text.decode("utf-8", "surrogateescape") if isinstance(text, bytes) else str(text)
    return _UNPRINTABLE.sub(_escape_char, text)


def shorten(text: object, limit: int = MAX_SHOWN) -> str:
    """``text`` for an error message: escaped (:func:`escape`) and at most ``limit``
    characters (a 10 MB token is not echoed back)."""
    text = escape(text)
    if len(text) <= limit:
        return text
    tail = limit // 3  # a path's end (the file's own name) says the most
    return f"{text[: limit - 20 - tail]}...{text[-tail:]} ({len(text)} characters)"


_LONG_TOKEN = re.compile(rf"\S{{{MAX_SHOWN + 1},}}")


def shorten_tokens(text: str) -> str:
    """Every over-long word of ``text`` shortened and every control character escaped: a
    message or log line never carries a 10 MB token or a raw newline back to the user,
    whatever raised it. Line breaks are kept (a usage message has several lines); a message
    that must be one line goes through :func:`escape` as a whole."""
    lines = (escape(line) for line in str(text).split("\n"))
    return _LONG_TOKEN.sub(lambda m: shorten(m.group()), "\n".join(lines))
