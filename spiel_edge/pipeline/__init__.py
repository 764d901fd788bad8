"""The per-acquisition pipeline (docs/pipeline.md, "Stages"): ``stages`` holds one module per
stage in data-flow order (preprocess -> detect -> memg -> features -> associate, scene ->
echo_timing -> echo_quality -> locate, uncertainty), ``learned`` the learned models in numba,
``staged`` the reference Pipeline composing the stages, ``compiled`` the same stages in one
numba call per acquisition, and ``factory`` builds the one a profile asks for."""

from spiel_edge.pipeline.staged import Pipeline, Result

__all__ = ["Pipeline", "Result"]
