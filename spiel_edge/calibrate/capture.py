"""Live, guided capture for calibration: the target at each listed position, M acquisitions each.

The session is anything with the DeviceSession streaming API (``start_stream``,
``acquisitions``, ``stop_stream``). Before each position ``before_position(i, p)`` runs: the
CLI asks the operator to place the target there and press Enter, or returns at once when a
robot moves it (``--no-prompt``). A board that sends its target-free scene (the virtual board
does) provides the background; otherwise one is captured first with the scene cleared.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np

from spiel_edge.errors import DeviceError
from spiel_edge.profile.schema import Profile
from spiel_edge.runtime.background_capture import background_of

log = logging.getLogger(__name__)

BeforePosition = Callable[[int, np.ndarray | None], None]  # position None: clear the scene
Progress = Callable[[int], None]  # acquisitions captured since the last call


def capture(
    session, n: int, n_samples: int, rate_hz: float, progress: Progress | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """``n`` acquisitions (n, channels, samples) and the board's background, if it sends one."""
    frames, background = [], None
    # exactly n: the board stops by itself, so none more is in flight when the host stops it
    session.start_stream(rate_hz=rate_hz, n_samples=n_samples, n_acquisitions=n)
    try:
        for acq in session.acquisitions(threading.Event()):
            frames.append(np.asarray(acq.samples, dtype=np.float64))
            if acq.background is not None:
                background = np.asarray(acq.background, dtype=np.float64)
            if progress is not None:
                progress(1)
            if len(frames) == n:
                break
    finally:
        session.stop_stream()
    shapes = {f.shape for f in frames}
    if len(shapes) != 1 or next(iter(shapes))[1] != n_samples:
        raise DeviceError(
            f"the board sent acquisitions of shape {sorted(shapes)}, expected (channels, {n_samples})"
        )
    return np.stack(frames), background


def capture_positions(
    session,
    profile: Profile,
    positions: np.ndarray,
    *,
    captures: int,
    before_position: BeforePosition,
    progress: Progress | None = None,
    rate_hz: float = 50.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames (P*M, channels, samples), backgrounds (same shape) and the target position of each."""
    n_samples = profile.acquisition.n_samples
    _, background = capture(session, 1, n_samples, rate_hz)  # does the board send its background?
    if background is None:
        before_position(-1, None)
        empty, _ = capture(session, captures, n_samples, rate_hz)
        background = background_of(empty)
    frames, backgrounds, truth = [], [], []
    for i, p in enumerate(np.asarray(positions, dtype=np.float64)):
        before_position(i, p)
        got, bg = capture(session, captures, n_samples, rate_hz, progress)
        frames.append(got)
        backgrounds.append(np.broadcast_to(bg if bg is not None else background, got.shape))
        truth.append(np.repeat(p[None], len(got), axis=0))
        log.info("position %d %s: %d acquisitions", i, p, len(got))
    return np.concatenate(frames), np.concatenate(backgrounds), np.concatenate(truth)
