"""Build a Pipeline with the associator a profile or the command line asks for."""

from __future__ import annotations

import logging

from spiel_edge.errors import ModelError
from spiel_edge.pipeline.compiled.fused import FusedPipeline
from spiel_edge.pipeline.iq3d import IqPipeline
from spiel_edge.pipeline.learned.toa_correction import build_echo_timing
from spiel_edge.pipeline.ranging import RangePipeline
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.pipeline.stages.associate import GeometricAssociator
from spiel_edge.profile.schema import Profile

log = logging.getLogger(__name__)


def build_associator(profile: Profile, method: str | None = None):
    """``onnx``/``auto``: the learned associator when its model loads, else a warning and the
    geometric one (never a crash); ``geometric``: the geometric one."""
    method = method or profile.associate.method
    if method == "geometric":
        return GeometricAssociator(profile)
    try:
        from spiel_edge.pipeline.learned.associate_onnx import OnnxAssociator
    except ImportError as exc:  # the learned associator is not built into this install
        log.warning("learned association unavailable (%s); using geometric association", exc)
        return GeometricAssociator(profile)
    try:
        return OnnxAssociator(profile)
    except ModelError as exc:
        log.warning("%s; using geometric association", exc)
        return GeometricAssociator(profile)


def build_pipeline(
    profile: Profile,
    association: str | None = None,
    toa_correction: str | None = None,
    *,
    fused: bool = True,
) -> Pipeline | FusedPipeline | RangePipeline | IqPipeline:
    """``toa_correction`` (auto|onnx|none) overrides the profile's ``echo_timing.toa_correction``;
    the fused path (same results as the staged one, less overhead) unless fused=False.
    One or two listening transducers: the ranging pipeline (pipeline/ranging.py); three or more
    with I/Q samples: the staged 3-D pipeline timed by the carrier phase (pipeline/iq3d.py)."""
    if int(profile.geometry.listening_mask().sum()) < 3:
        return RangePipeline(profile)
    kind = IqPipeline if profile.acquisition.signal == "iq" else Pipeline
    staged = kind(
        profile,
        build_associator(profile, association),
        echo_timing=build_echo_timing(profile, toa_correction),
    )
    return FusedPipeline(staged) if fused and kind is Pipeline else staged
