"""The staged pipeline, the reference: frames in, one Result (position or reason) out, every
stage a call of its own (``pipeline/stages/``). The compiled path (``pipeline/compiled/``) runs
the same stages in one call and must agree with it bit for bit; it reads what it needs through
:meth:`Pipeline.kernel_constants` and the public attributes below."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.pipeline.learned.toa_correction import build_echo_timing
from spiel_edge.pipeline.stages.associate import GeometricAssociator
from spiel_edge.pipeline.stages.detect import detect
from spiel_edge.pipeline.stages.echo_quality import echo_quality
from spiel_edge.pipeline.stages.echo_timing import EchoTiming, timing_delays
from spiel_edge.pipeline.stages.error_model import apply_error_model
from spiel_edge.pipeline.stages.features import TOA_COLUMN, echo_features
from spiel_edge.pipeline.stages.locate import locate
from spiel_edge.pipeline.stages.memg import WINDOW_AFTER, WINDOW_BEFORE, fit_memg
from spiel_edge.pipeline.stages.preprocess import preprocess
from spiel_edge.pipeline.stages.scene import SceneAssociator, is_double_reflection, shared_echoes
from spiel_edge.pipeline.stages.scene_geometry import distance3
from spiel_edge.pipeline.stages.split import split_merged
from spiel_edge.pipeline.stages.static_scene import load_static_model
from spiel_edge.pipeline.stages.uncertainty import covariance_kernel
from spiel_edge.profile.schema import Profile
from spiel_edge.profile.specs import MAX_TARGETS_LIMIT

log = logging.getLogger(__name__)

Associator = Callable[[np.ndarray, np.ndarray], np.ndarray]


@runtime_checkable
class CompiledForm(Protocol):
    """A collaborator of the Pipeline (associator, echo timing, scene) the compiled path can
    run: its constants by the names of ``pipeline/compiled/abi.py``, or None when this
    instance needs the staged path."""

    def kernel_constants(self) -> dict | None: ...


# echo_timing runs per target inside locate; its time is reported apart from locate's
STAGES = ("preprocess", "detect", "memg", "features", "associate", "echo_timing", "locate")

# Why a record has no position (the ``reason`` field).
REASON_TOO_FEW_CHANNELS = "fewer than 3 channels with echoes"
REASON_NO_CONSISTENT_ECHOES = "no echo combination consistent with one target"
REASON_SOLVE_FAILED = "ellipsoid intersection did not converge in front of the array"
REASON_FLAT_FRAME = "frame is flat (all samples equal): no signal"
REASON_SATURATED = "frame is saturated"


@dataclass
class Target:
    """One target found in an acquisition (the record's ``targets`` entries, best first)."""

    position_mm: np.ndarray  # (3,)
    covariance_mm2: np.ndarray  # (3, 3), symmetric positive semi-definite
    residual_mm: float
    matched: list[int | None]  # per channel: index into the record's echoes, or None
    score: float  # higher is better; comparable within one acquisition
    track_id: int | None = None  # set by the tracker
    timing: str | None = None  # I/Q boards: what timed its echoes (pipeline/iq3d.py); else None

    def record(self) -> dict:
        out = {
            "position_mm": _rounded(self.position_mm.tolist(), 2),
            "covariance_mm2": [_rounded(r, 3) for r in self.covariance_mm2.tolist()],
            "residual_mm": round(float(self.residual_mm), 3),
            "matched": self.matched,
            "score": round(float(self.score), 4),
        }
        if self.track_id is not None:
            out["track_id"] = int(self.track_id)
        if self.timing is not None:
            out["timing"] = self.timing
        return out


def _rounded(values: list[float], digits: int) -> list[float]:
    """Three values rounded (no comprehension: this runs for every target of every record)."""
    a, b, c = values
    return [round(a, digits), round(b, digits), round(c, digits)]


@dataclass
class Result:
    """What the pipeline makes of one acquisition."""

    position_mm: np.ndarray | None
    reason: str | None
    residual_mm: float | None
    echoes: list[list[float]]  # per channel: echo ToAs in samples, ascending
    matched: list[int | None]  # per channel: index into echoes, or None
    features: np.ndarray = field(repr=False)  # (channels, max_echoes, 8)
    counts: np.ndarray = field(repr=False)
    timings_us: dict[str, float] = field(default_factory=dict, repr=False)
    targets: list[Target] = field(default_factory=list)  # best first; filled by the scene stage

    def record(self) -> dict:
        """JSON-ready fields shared by replay and run records."""
        return {
            "position_mm": None
            if self.position_mm is None
            else [round(v, 2) for v in self.position_mm.tolist()],
            "reason": self.reason,
            "residual_mm": None if self.residual_mm is None else round(float(self.residual_mm), 3),
            "echoes": [[round(t, 3) for t in ch] for ch in self.echoes],
            "matched": self.matched,
            "targets": [t.record() for t in self.targets],
        }


def front_stages(p: Profile, frames, background, clock) -> tuple:
    """preprocess -> detect -> memg (-> split) -> features of one acquisition (envelope or RF
    frames, the background already chosen): (features, counts, the clock after each stage,
    the cleaned envelope).
    Shared by the 3-D pipeline and the ranging one (pipeline/ranging.py)."""
    acq = p.acquisition
    y = preprocess(
        frames,
        background,
        blind_zone=p.preprocess.blind_zone_samples,
        rf=acq.signal == "rf",
        carrier_cycles_per_sample=acq.carrier_hz / acq.sample_rate_hz,
    )
    t1 = clock()
    d = p.detect
    peaks, counts = detect(
        y,
        threshold=d.threshold,
        hysteresis=d.hysteresis,
        min_amplitude=d.min_amplitude,
        max_echoes=d.max_echoes,
        first_sample=p.preprocess.blind_zone_samples,
        checked=True,  # preprocess validated the acquisition: once, not in every stage
    )
    t2 = clock()
    m = p.memg
    params = fit_memg(
        y,
        peaks,
        counts,
        mu_window=m.mu_window,
        max_iterations=m.max_iterations,
        window_before=m.window_before,
        window_after=m.window_after,
        checked=True,
    )
    if m.split_merged:
        peaks, counts, params = split_merged(
            y,
            peaks,
            counts,
            params,
            min_sigma=m.split_min_sigma,
            max_cost_ratio=m.split_max_cost_ratio,
            mu_window=m.mu_window,
            max_iterations=m.max_iterations,
            checked=True,
        )
    t3 = clock()
    feats = echo_features(y, params, peaks, m.toa, checked=True)
    return feats, counts, (t1, t2, t3, clock()), y


class Pipeline:
    """preprocess -> detect -> memg -> features -> associate -> locate for one profile."""

    #: the compiled path (pipeline/compiled/fused.py) computes what ``process`` does; a
    #: subclass that keeps that true says so in its own body, any other runs staged
    compiled_equivalent = True

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if "compiled_equivalent" not in vars(cls):
            cls.compiled_equivalent = False

    def __init__(
        self,
        profile: Profile,
        associator: Associator | None = None,
        *,
        saturation: float = 65535.0,
        max_targets: int | None = None,
        echo_timing: EchoTiming | None = None,
    ):
        self.profile = profile
        self.associator = associator or GeometricAssociator(profile)
        self.echo_timing = echo_timing or build_echo_timing(profile)
        self._echo_timing_ns, self._clock = 0, no_clock
        self.set_max_targets(profile.scene.max_targets if max_targets is None else max_targets)
        self.static_model = load_static_model(profile)  # stands in for a missing background
        self.saturation = saturation  # full scale of the board's samples (u16 envelopes)
        g = profile.geometry
        self.channels_mm = np.ascontiguousarray(g.channels_mm, dtype=np.float64)
        self.emitter_mm = np.ascontiguousarray(g.emitter_mm, dtype=np.float64)
        self.facing = np.ascontiguousarray(g.facing, dtype=np.float64)
        # per-channel delays (samples) of the ToA the echo-timing step gives
        self.delays = timing_delays(profile) if self.echo_timing.active else g.delays()

    def set_max_targets(self, k: int) -> None:
        """Report up to ``k`` targets per acquisition (1 .. MAX_TARGETS_LIMIT)."""
        if not (isinstance(k, int | np.integer) and 1 <= k <= MAX_TARGETS_LIMIT):
            raise InputError(
                f"max_targets must be an integer in [1, {MAX_TARGETS_LIMIT}], got {k!r}"
            )
        self.max_targets = int(k)
        sc = self.profile.scene
        self.scene = SceneAssociator(
            self.associator,
            self.max_targets,
            sc.max_cost_mm,
            sc.share_penalty_mm,
            sc.extra_min_channels,
            sc.selection,
            sc.missing_penalty_mm,
            sc.keep_best,
        )

    def check_shape(self, frames: np.ndarray, what: str = "frames") -> None:
        n_ch, n_t = self.profile.geometry.n_channels, self.profile.acquisition.n_samples
        if np.shape(frames) != (n_ch, n_t):
            raise InputError(
                f"{what} has shape {np.shape(frames)}, profile {self.profile.name!r} expects ({n_ch}, {n_t})"
            )

    def process(
        self, frames: np.ndarray, background: np.ndarray | None = None, *, timed: bool = False
    ) -> Result:
        """Run every stage on one acquisition (channels, samples)."""
        p = self.profile
        self.check_shape(frames)
        if background is not None:
            self.check_shape(background, "background")
        clock = time.perf_counter_ns if timed else no_clock
        t0 = clock()
        if not p.preprocess.background_subtraction:
            background = None
        elif background is None:
            background = self.static_model
        feats, counts, (t1, t2, t3, t4), _ = front_stages(p, frames, background, clock)
        hypotheses = self.scene(feats, counts)
        t5 = clock()
        self._clock, self._echo_timing_ns = clock, 0
        result = self.locate_hypotheses(feats, counts, hypotheses, np.asarray(frames), background)
        if p.scene.error_model:
            captured = background is not None and background is not self.static_model
            apply_error_model(result, p.scene.error_model, self.facing, captured)
        t6 = clock()
        if timed:
            stamps = (t0, t1, t2, t3, t4, t5, t5 + self._echo_timing_ns, t6)
            result.timings_us = {s: (stamps[i + 1] - stamps[i]) / 1e3 for i, s in enumerate(STAGES)}
            result.timings_us["end_to_end"] = (t6 - t0) / 1e3
        return result

    def locate_hypotheses(
        self,
        feats: np.ndarray,
        counts: np.ndarray,
        hypotheses: list,
        raw: np.ndarray,
        background: np.ndarray | None,
    ) -> Result:
        toa = feats[:, :, TOA_COLUMN]
        echoes = [[float(v) for v in toa[c, : counts[c]]] for c in range(len(counts))]
        first = hypotheses[0][0]
        base = {"features": feats, "counts": counts}
        targets = self._targets(feats, hypotheses, raw, background)
        if not targets:
            match_list = [int(m) if m >= 0 else None for m in first]
            reason = REASON_SOLVE_FAILED if (first >= 0).sum() >= 3 else self.why_empty(raw, counts)
            return Result(None, reason, None, echoes, match_list, **base)
        best = targets[0]
        return Result(
            best.position_mm, None, best.residual_mm, echoes, best.matched, targets=targets, **base
        )

    def _targets(self, feats, hypotheses, raw, background) -> list[Target]:
        """Locate every hypothesis; share echoes where two targets sit at one range; drop
        double reflections and failed solves (docs/scene.md)."""
        sc, g = self.profile.scene, self.profile.geometry
        paths_all = (feats[:, :, TOA_COLUMN] - self.delays[:, None]) * self.profile.mm_per_sample
        taken = np.zeros(paths_all.shape, dtype=np.bool_)
        for matched, _ in hypotheses:
            taken[np.flatnonzero(matched >= 0), matched[matched >= 0]] = True
        out: list[tuple[Target, np.ndarray]] = []
        for i, (matched, cost) in enumerate(hypotheses):
            located = self.locate_target(feats, matched, cost, raw, background)
            if located is None:
                continue
            if i > 0 and (matched < 0).any():
                more = shared_echoes(
                    matched,
                    located[0].position_mm,
                    paths_all,
                    taken,
                    self.channels_mm,
                    self.emitter_mm,
                    g.listening_mask(),
                    sc.share_tolerance_mm,
                )
                if (more != matched).any():
                    located = self.locate_target(feats, more, cost, raw, background) or located
            target, paths = located
            if any(
                distance3(target.position_mm, other.position_mm) < sc.min_separation_mm
                for other, _ in out
            ):
                continue  # the same target again, from a partly different echo combination
            if any(
                is_double_reflection(
                    paths,
                    other_paths,
                    other.position_mm,
                    self.emitter_mm,
                    self.facing,
                    sc.double_tolerance_mm,
                )
                for other, other_paths in out
            ):
                continue
            out.append((target, paths))
        return [t for t, _ in out]

    def locate_target(
        self, feats, matched, cost, raw, background
    ) -> tuple[Target, np.ndarray] | None:
        """One target from its matched echoes, re-timed by the echo-timing step, with its
        covariance; None when the solve fails."""
        use = matched >= 0
        if use.sum() < 3:
            return None
        toa = feats[:, :, TOA_COLUMN]
        rows = np.arange(len(matched)), np.maximum(matched, 0)
        picked = np.where(use, toa[rows], np.nan)
        start = self._clock()
        picked = self.echo_timing(raw, background, picked)  # this target's ToAs, re-timed
        self._echo_timing_ns += self._clock() - start
        weights, shift = echo_quality(
            raw, background, picked, feats[rows][:, 0], self.profile.locate
        )
        if self.echo_timing.active:  # the echo timing replaces echo quality's ToA shift
            shift = 0.0
        picked, weights, shift, timing = self.phase_timing(
            feats, matched, use, picked, weights, shift
        )
        paths = (picked + shift - self.delays) * self.profile.mm_per_sample
        pos, rms, ok = locate(
            paths, self.channels_mm, self.emitter_mm, self.facing, use, weights=weights
        )
        if not ok:
            return None
        sigma_mm = self.profile.mm_per_sample / weights
        cov = np.empty((3, 3))  # arrays checked above: the kernel directly (hot path)
        covariance_kernel(
            pos,
            paths,
            sigma_mm,
            use & np.isfinite(paths),
            self.channels_mm,
            self.emitter_mm,
            self.covariance_scale(background),
            self.profile.scene.covariance_floor_mm,
            cov,
        )
        match_list = [int(m) if m >= 0 else None for m in matched]
        score = -cost if np.isfinite(cost) else 0.0
        return Target(pos, cov, rms, match_list, score, timing=timing), paths

    def phase_timing(self, feats, matched, use, picked, weights, shift) -> tuple:
        """(ToAs, weights, shift, timing) of one target's matched echoes: as given here (no
        carrier phase, timing None); an I/Q board's pipeline refines them (pipeline/iq3d.py)."""
        return picked, weights, shift, None

    def covariance_scale(self, background: np.ndarray | None) -> float:
        """The covariance's scale for a captured background, or for none (the static model
        standing in)."""
        sc = self.profile.scene
        captured = background is not None and background is not self.static_model
        return float(sc.covariance_scale if captured else sc.covariance_scale_no_background)

    def kernel_constants(self) -> dict | None:
        """What the compiled path needs to run this pipeline's stages after the front ones,
        by the names of its argument table (``pipeline/compiled/abi.py``): each
        collaborator's own (associator, echo timing, scene: their ``kernel_constants``), then
        the pipeline's geometry and settings. None when a collaborator has no compiled form;
        then the staged path runs. A subclass that changes what a stage computes returns
        None here (or from the collaborator's ``kernel_constants``)."""
        m = self.profile.memg
        if (m.window_before, m.window_after) != (WINDOW_BEFORE, WINDOW_AFTER):
            return None  # the compiled front fits the default window only
        parts = [self.associator, self.echo_timing, self.scene]
        found = [p.kernel_constants() if isinstance(p, CompiledForm) else None for p in parts]
        if any(f is None for f in found):
            return None
        loc, sc = self.profile.locate, self.profile.scene
        quality = (
            loc.toa_sigma_samples,
            loc.toa_sigma_per_background,
            loc.toa_sigma_alpha_counts,
            loc.toa_shift_background_after,
            loc.toa_shift_background_before,
        )
        listening = self.profile.geometry.listening_mask()
        return {
            **found[0],
            **found[1],
            **found[2],
            "quality": np.array(quality),
            "delays": self.delays,
            "channels": self.channels_mm,
            "emitter": self.emitter_mm,
            "facing": self.facing,
            "cov_floor": sc.covariance_floor_mm,
            "share_tol": sc.share_tolerance_mm,
            "min_separation": sc.min_separation_mm,
            "double_tol": sc.double_tolerance_mm,
            "share_listening": np.ascontiguousarray(listening, dtype=np.bool_),
        }

    def why_empty(self, raw: np.ndarray, counts: np.ndarray) -> str:
        if raw.size and np.mean(raw >= self.saturation) > 0.5:
            return REASON_SATURATED
        if raw.size and np.ptp(raw) == 0:
            return REASON_FLAT_FRAME
        if int((counts > 0).sum()) < 3:
            return REASON_TOO_FEW_CHANNELS
        return REASON_NO_CONSISTENT_ECHOES


def no_clock() -> int:
    return 0
