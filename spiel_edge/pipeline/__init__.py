"""The per-acquisition pipeline, one module per stage in data-flow order: preprocess -> detect
-> memg -> features -> associate (scene: several targets) -> echo_timing (+ toa_correction)
-> echo_quality -> locate (+ uncertainty); ``run`` composes them, ``fused`` runs the front
stages as one compiled call."""

from spiel_edge.pipeline.staged import Pipeline, Result

__all__ = ["Pipeline", "Result"]
