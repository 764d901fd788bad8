"""Geometry rules beyond shapes and types: a layout the solver cannot use gives confident
nonsense, so it is refused up front with the key the user wrote (``geometry.channels_mm``,
``geometry.delay_samples``, ...). Used for profiles, calibrations and board configs alike."""

from __future__ import annotations

import numpy as np

from spiel_edge.errors import ConfigError

MAX_CHANNELS = 64
MAX_EXTENT_MM = 10_000.0  # 10 m: no transducer board is larger
MIN_SEPARATION_MM = 0.5  # two receivers closer than this are one
MIN_SPREAD_MM = 1.0  # the array's second principal extent: below, the receivers are collinear
MIN_FACING_OUT_OF_PLANE = 0.2  # |cos| between facing and a planar array's normal


def check_geometry(g, n_samples: int, origin: str) -> None:
    """ConfigError naming the key for a layout that cannot locate a target."""

    def need(ok: bool, message: str) -> None:
        if not ok:
            raise ConfigError(f"{origin}: {message}")

    channels = np.asarray(g.channels_mm, dtype=np.float64)
    n = channels.shape[0]
    need(n <= MAX_CHANNELS, f"geometry.channels_mm has {n} channels; at most {MAX_CHANNELS}")
    for key, arr in (("channels_mm", channels), ("emitter_mm", np.asarray(g.emitter_mm))):
        worst = float(np.max(np.abs(arr))) if arr.size else 0.0
        need(
            worst <= MAX_EXTENT_MM,
            f"geometry.{key} has a coordinate of {worst:g} mm; at most {MAX_EXTENT_MM:g} mm",
        )
    facing = np.asarray(g.facing, dtype=np.float64)
    need(float(np.linalg.norm(facing)) > 1e-9, "geometry.facing must not be the zero vector")
    delays = np.asarray(g.delays(), dtype=np.float64)
    worst_delay = float(np.max(np.abs(delays))) if delays.size else 0.0
    need(
        worst_delay <= n_samples,
        f"geometry.delay_samples has {worst_delay:g}; must be within +-{n_samples} "
        "(acquisition.n_samples)",
    )
    listening = np.flatnonzero(g.listening_mask())
    points = channels[listening]
    for a in range(len(points)):
        for b in range(a + 1, len(points)):
            gap = float(np.linalg.norm(points[a] - points[b]))
            need(
                gap >= MIN_SEPARATION_MM,
                f"geometry.channels_mm: channels {listening[a]} and {listening[b]} coincide "
                f"({gap:.3g} mm apart); listening receivers must be distinct",
            )
    _check_spread(points, np.asarray(g.emitter_mm, dtype=np.float64), facing, need)


def _check_spread(points: np.ndarray, emitter: np.ndarray, facing: np.ndarray, need) -> None:
    """At least 3 independent baselines: the receivers and the emitter must span a plane
    (collinear ones leave the target free to turn about their line), and a planar array must
    face out of its plane (else front and back cannot be told apart)."""
    if len(points) == 2:  # a pair: bearing in the plane of its baseline and the facing
        base = (points[1] - points[0]) / np.linalg.norm(points[1] - points[0])
        cosine = abs(float(base @ facing)) / float(np.linalg.norm(facing))
        need(
            cosine <= 1.0 - MIN_FACING_OUT_OF_PLANE,
            "geometry.facing lies along the two listening transducers' baseline; it must "
            "point away from it",
        )
    if len(points) < 3:
        return  # one or two transducers: range (and bearing), no 3-D spread needed
    cloud = np.vstack([points, emitter])
    singular = np.linalg.svd(cloud - cloud.mean(axis=0), compute_uv=False)
    need(
        singular[1] >= MIN_SPREAD_MM,
        "geometry.channels_mm: the listening receivers and the emitter lie on one line; "
        "a 3-D position needs at least 3 independent baselines (receivers spread in a plane)",
    )
    if singular[2] < MIN_SPREAD_MM:  # planar: facing must leave the plane
        normal = np.linalg.svd(cloud - cloud.mean(axis=0))[2][2]
        cosine = abs(float(normal @ facing)) / float(np.linalg.norm(facing))
        need(
            cosine >= MIN_FACING_OUT_OF_PLANE,
            "geometry.facing lies in the plane of the array; it must point out of it",
        )
