"""The per-acquisition pipeline, one module per stage in data-flow order:
preprocess -> detect -> memg -> features -> associate -> locate (composed in ``run``)."""

from spiel_edge.pipeline.run import Pipeline, Result

__all__ = ["Pipeline", "Result"]
