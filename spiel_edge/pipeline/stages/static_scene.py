"""Without a background capture: a model of the static scene stands in for it.

The emitter's ring-down, the direct crosstalk and the board's mount are the same in every
acquisition of one board; the per-sample median over many target-free captures (the training
sessions' background captures, ``tools/train/build_static_model.py``) is largely exactly that, and
their median absolute deviation says how much it varies. ``[scene] static_model`` names the
model (a file in ``spiel_edge/models`` or a path); the stand-in background is
``median + static_mad_factor * mad``. A captured background is always used instead when given.

A model that is missing, unreadable or of another shape gives one warning and no stand-in
(the frames are then used as they are, as before).
"""

from __future__ import annotations

import logging
from importlib import resources
from pathlib import Path

import numpy as np

from spiel_edge.profile.schema import Profile

log = logging.getLogger(__name__)


def model_path(name: str) -> Path:
    candidate = Path(name)
    if candidate.is_absolute() or candidate.exists():
        return candidate
    return Path(str(resources.files("spiel_edge") / "models" / name))


def load_static_model(profile: Profile) -> np.ndarray | None:
    """The stand-in background (channels, samples) of ``profile``, or None."""
    name = profile.scene.static_model
    if not name:
        return None
    path = model_path(name)
    shape = (profile.geometry.n_channels, profile.acquisition.n_samples)
    try:
        with np.load(path) as data:
            median = np.asarray(data["median"], dtype=np.float64)
            mad = np.asarray(data["mad"], dtype=np.float64)
    except (OSError, KeyError, ValueError) as exc:
        log.warning("static scene model %s unusable (%s); frames used without one", path, exc)
        return None
    if median.shape != shape or mad.shape != shape:
        log.warning(
            "static scene model %s is %s, profile %r needs %s; frames used without one",
            path,
            median.shape,
            profile.name,
            shape,
        )
        return None
    level = median + profile.scene.static_mad_factor * mad
    if not np.all(np.isfinite(level)):
        log.warning("static scene model %s holds non-finite values; frames used without one", path)
        return None
    level = np.clip(level, 0.0, None)
    level.setflags(write=False)
    return level


def static_model_arrays(backgrounds: np.ndarray) -> dict[str, np.ndarray]:
    """Median and median absolute deviation per sample of target-free captures
    (captures, channels, samples)."""
    b = np.asarray(backgrounds, dtype=np.float64)
    median = np.median(b, axis=0)
    return {"median": median, "mad": np.median(np.abs(b - median), axis=0)}
