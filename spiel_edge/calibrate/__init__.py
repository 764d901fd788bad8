"""Calibration: receiver positions, per-channel delays and speed of sound from targets at
known positions (``spiel-edge calibrate``)."""

from spiel_edge.calibrate.echoes import channel_offsets, extract_echoes, pick_echoes
from spiel_edge.calibrate.fit import Calibration, calibrate_echoes, calibrate_frames
from spiel_edge.calibrate.solve import FIXABLE, CalibrationResult, Observations, predict_toa, solve
from spiel_edge.calibrate.sources import LabelledSet, load_recordings, read_positions

__all__ = [
    "FIXABLE",
    "Calibration",
    "CalibrationResult",
    "LabelledSet",
    "Observations",
    "calibrate_echoes",
    "calibrate_frames",
    "channel_offsets",
    "extract_echoes",
    "load_recordings",
    "pick_echoes",
    "predict_toa",
    "read_positions",
    "solve",
]
