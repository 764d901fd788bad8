"""The profile ``run`` uses, and where its geometry came from: ``--calibration`` over the
board's stored config (read through :func:`flash.pull <spiel_edge.board_config.flash.pull>`)
over the named profile. Out of flash.py, which flashes configs (issue 42: names by meaning);
above ``profile/`` in the layers, because it reads the board."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from spiel_edge.board_config.flash import pull
from spiel_edge.board_config.schema import profile_with_board
from spiel_edge.errors import ConfigError, DeviceError
from spiel_edge.profile.schema import Profile, apply_calibration, load_profile
from spiel_edge.protocol.errors import ErrorCode

log = logging.getLogger(__name__)


def profile_from_board(session: Any, base_profile: Profile) -> Profile:
    """The profile to run with: ``base_profile`` with what the board stores, or unchanged
    (with a warning) when the board holds no config, an unusable one, or cannot store one."""
    return _board_profile(session, base_profile)[0]


def _board_profile(session: Any, base: Profile) -> tuple[Profile, str | None]:
    """``base`` with the board's config and the board's name, or ``(base, None)``."""
    try:
        config = pull(session)
        if config is None:
            log.info("the board holds no config; using profile %r", base.name)  # normal when new
            return base, None
        return profile_with_board(base, config), config["board"]["name"]
    except ConfigError as exc:
        log.warning("the board's config is not usable, using profile %r: %s", base.name, exc)
    except DeviceError as exc:  # the session's DeviceRequestError carries the board's code
        if getattr(exc, "code", None) != ErrorCode.UNSUPPORTED:
            raise
        log.info("the board cannot store a config; using profile %r", base.name)
    return base, None


def run_profile(
    session: Any,
    profile_name: str,
    calibration: str | Path | None = None,
    *,
    use_board: bool = True,
    resolved: tuple[Profile, Profile] | None = None,
) -> tuple[Profile, str]:
    """The profile ``run`` uses and where its geometry came from. Precedence: ``calibration``
    over the board's stored config (unless ``use_board`` is false) over ``profile_name``.
    ``resolved``: ``profile_name`` loaded and that with the calibration applied, when the
    caller has them already (runtime/live.py): reused unless the board's config changes them."""
    base, calibrated = resolved if resolved is not None else (load_profile(profile_name), None)
    profile, board = base, None
    source = f"profile {profile.name!r}"
    if use_board:
        profile, board = _board_profile(session, profile)
        if board is not None:
            source = f"board {board!r}"
    if calibration:
        profile = (
            calibrated
            if calibrated is not None and board is None
            else apply_calibration(profile, calibration)
        )
        source = f"calibration {str(calibration)!r} over {source}"
    log.info("geometry from %s", source)
    return profile, source
