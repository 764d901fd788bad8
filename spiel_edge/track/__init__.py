"""Multi-target tracking along the data flow: targets per acquisition -> tracks -> outputs.

``Tracker(spec).update(targets, t_s)`` (tracker.py) runs the compiled step (step.py): an
interacting multiple model per track (imm.py: a near-static and a constant-velocity Kalman
filter, kalman.py), Mahalanobis gating and a global
assignment (assign.py, Hungarian). See docs/tracking.md.
"""

from spiel_edge.track.tracker import MAX_TARGETS, Track, Tracker

__all__ = ["MAX_TARGETS", "Track", "Tracker"]
