"""Board config over a device session: pull, push to staging with read-back, commit.

The session provides ``read_config(source=ConfigSource.ACTIVE) -> bytes``,
``write_config(blob, progress=None)``, ``commit_config(expected_crc)`` and
``config_status()``. The commit is the board's: it writes the inactive flash slot, verifies
it and only then makes it active, so a power cut at any flash operation leaves the old config
in force; here we refuse to commit anything that is not a valid config and check afterwards
that the active slot holds exactly what was staged.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from crc32c import crc32c

from spiel_edge.board_config.schema import decode, encode
from spiel_edge.errors import ConfigError, DeviceDisconnectedError, DeviceError
from spiel_edge.protocol import ConfigSource
from spiel_edge.protocol.errors import ErrorCode

log = logging.getLogger(__name__)


def pull(session: Any, *, staging: bool = False) -> dict[str, Any] | None:
    """The board's active (or staged) config, or None when it has none."""
    source = ConfigSource.STAGING if staging else ConfigSource.ACTIVE
    try:
        blob = session.read_config(source=source)
    except DeviceError as exc:  # the session's DeviceRequestError carries the board's code
        if getattr(exc, "code", None) == ErrorCode.NOT_FOUND:
            return None
        raise
    if not blob:
        return None
    return decode(blob, origin="board staging" if staging else "board")


def push(
    session: Any, config: dict[str, Any], progress: Callable[[int], None] | None = None
) -> int:
    """Write ``config`` to the board's staging area, read it back, compare; returns its CRC-32C."""
    blob = encode(config)
    session.write_config(blob, progress=progress)
    back = session.read_config(source=ConfigSource.STAGING)
    if back != blob:
        where = next(
            (i for i, (a, b) in enumerate(zip(back, blob, strict=False)) if a != b),
            min(len(back), len(blob)),
        )
        raise DeviceError(
            f"staged config read back differs from what was written at byte {where} "
            f"({len(back)} vs {len(blob)} bytes); nothing was committed"
        )
    crc = crc32c(blob)
    log.info("staged %d bytes, CRC-32C %08x", len(blob), crc)
    return crc


def commit(session: Any, expected_crc: int | None = None) -> int:
    """Make the staged config persistent; returns its CRC-32C. Without ``expected_crc`` the
    staged bytes are read back and must decode as a valid config."""
    status = session.config_status() if hasattr(session, "config_status") else None
    if status is not None and not status.staged_length:
        raise ConfigError(
            "nothing is staged on the board: `spiel-edge config push FILE` first, then commit"
        )
    if expected_crc is None:
        staged = session.read_config(source=ConfigSource.STAGING)
        decode(staged, origin="board staging")
        expected_crc = crc32c(staged)
    try:
        session.commit_config(expected_crc)
    except DeviceDisconnectedError as exc:
        raise DeviceDisconnectedError(
            f"the board went away during the commit ({exc}); its flash keeps the previous config "
            "active and the staged one is lost: push and commit again"
        ) from exc
    active = session.read_config(source=ConfigSource.ACTIVE)
    if crc32c(active) != expected_crc:
        raise DeviceError(
            f"after the commit the active config has CRC {crc32c(active):08x}, expected {expected_crc:08x}"
        )
    return expected_crc
