"""Board records that prove which board sent them: an HMAC-SHA256 tag per record.

Each board has its own secret key (a file: 32 random bytes as hex, e.g. ``openssl rand -hex
32``), named in the robot file (``auth_key_file``) for ``fuse`` and given to that board's
``run --zenoh KEY --zenoh-auth-key FILE``. The tag covers the record's bytes and the key
expression it is published on, and rides in the Zenoh sample's attachment, so the record
itself (JSON) is unchanged for every other subscriber.

Why a tag per record, not only Zenoh's own authentication: it holds end to end (through
routers and bridges, where the fusing session sees only its router, not the board), binds a
record to its board's key expression, needs no dependency beyond the standard library and
costs about 2 µs per record. Zenoh's mTLS and access control (docs/security.md) stay the
transport's defence: who may connect, and confidentiality on the wire. What it does not do:
the fusing computer holds every board's key (whoever controls it can forge any board), and a
board's own computer, compromised, signs whatever it likes as that board (docs/security.md).
Replays are refused by ``fuse``: a record's ``host_time`` must be within a second of its
arrival, and a tag seen among a board's recent ones is refused.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import stat
from collections import deque
from pathlib import Path

from spiel_edge.errors import ConfigError

MAGIC = b"SEH1"  # attachment: MAGIC + 32-byte tag
DOMAIN = b"spiel-edge/record/1\n"
MIN_KEY_BYTES = 16
MAX_KEY_FILE_BYTES = 4096
RECENT_TAGS = 512  # per board: > 1 s of records at any rate a board runs


def load_key(path: str | Path, what: str) -> bytes:
    """The secret in ``path`` (hex, 32+ digits; white space ignored). ConfigError in one line
    that never shows the file's content: unreadable, readable by every user, or not a key."""
    path = Path(path)
    try:
        st = path.stat()
        if st.st_size > MAX_KEY_FILE_BYTES:
            raise ConfigError(f"{what} {path}: not a key file (too large)")
        text = path.read_text(encoding="ascii", errors="strict")
    except ConfigError:
        raise
    except (OSError, UnicodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else "not text"
        raise ConfigError(f"{what} {path}: cannot read the key file ({reason})") from None
    if stat.S_IMODE(st.st_mode) & stat.S_IROTH and os.name == "posix":
        raise ConfigError(f"{what} {path}: the key file is readable by every user (chmod 600)")
    try:
        key = bytes.fromhex("".join(text.split()))
    except ValueError:
        key = b""
    if len(key) < MIN_KEY_BYTES:
        raise ConfigError(
            f"{what} {path}: not a key (expected {2 * MIN_KEY_BYTES}+ hex digits, "
            "e.g. from `openssl rand -hex 32`)"
        )
    return key


def tag(key: bytes, key_expr: str, payload: bytes) -> bytes:
    return hmac.new(key, DOMAIN + key_expr.encode() + b"\n" + payload, hashlib.sha256).digest()


def attachment(key: bytes, key_expr: str, payload: bytes) -> bytes:
    """What ``run --zenoh-auth-key`` attaches to each record it publishes."""
    return MAGIC + tag(key, key_expr, payload)


class Verifier:
    """One board's key: ``check(payload, attachment)`` -> None when the record is that
    board's (and not a replay of a recent one), else why not (a few words)."""

    def __init__(self, key: bytes, key_expr: str):
        self._key = key
        self._key_expr = key_expr
        self._recent: deque[bytes] = deque(maxlen=RECENT_TAGS)
        self._seen: set[bytes] = set()

    def check(self, payload: bytes, attached: bytes | None) -> str | None:
        if not attached or len(attached) != len(MAGIC) + 32 or not attached.startswith(MAGIC):
            return "forged"  # unsigned, or not our tag
        got = attached[len(MAGIC) :]
        if not hmac.compare_digest(got, tag(self._key, self._key_expr, payload)):
            return "forged"
        if got in self._seen:
            return "replayed"
        if len(self._recent) == self._recent.maxlen:
            self._seen.discard(self._recent[0])
        self._recent.append(got)
        self._seen.add(got)
        return None
