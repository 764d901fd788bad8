"""The compiled path's kernel ABI: every constant the kernels take, declared once.

A pipeline's constants reach the kernels as ``ints`` (the search's and echo timing's integer
settings, :data:`INTS`) and four buffers by dtype plus a ``layout`` (:data:`CONSTANTS`, the
table of :mod:`spiel_edge._abi`): numba's dispatch costs about 65 ns per array argument, and
45 arguments took 3 us. :func:`kernel_config` builds them from
``Pipeline.kernel_constants()`` (values by these names), and the kernels read them back with
the view functions below. Each name list below fixes its constants' order; the slot numbers
(``L_*``, ``I_*``, ``F_*``, ``S_*``, ``FI_*``, ``FF_*``) follow it, and the view functions
and the kernels' parameter lists are checked against it (tests/core/test_abi.py).
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np

from spiel_edge._abi import Field, Table
from spiel_edge._jit import jit
from spiel_edge.pipeline.learned.mlp import WEIGHTS
from spiel_edge.pipeline.learned.tree_ensemble import DENSE
from spiel_edge.pipeline.stages.features import TOA_CODES

log = logging.getLogger(__name__)

F64, F32, I64, FLAGS = np.float64, np.float32, np.int64, np.bool_
BUFFERS = (F64, F32, I64, FLAGS)  # the kernels' buffer arguments, in this order

# the modes, by name (``Pipeline.kernel_constants()`` gives the names)
PRIORS = ("none", "mlp")  # the association's score prior: none (geometric) or the MLP's
PRIOR_NONE, PRIOR_MLP = range(len(PRIORS))
TIMINGS = ("none", "refine", "trees")  # echo timing: off, refined, refined and corrected
TIMING_NONE, TIMING_REFINE, TIMING_TREES = range(len(TIMINGS))

# ints[]: the search's and echo timing's integers
INTS = ("min_channels", "exhaustive", "prior", "timing", "blind", "half_window", "log")
I_MIN_CHANNELS, I_EXHAUSTIVE, I_PRIOR, I_TIMING, I_BLIND, I_HALF_WINDOW, I_LOG = range(len(INTS))
# the "floats" array's entries
FLOATS = ("mm_per_sample", "strength", "score_weight", "limit", "cov_floor")
F_MM_PER_SAMPLE, F_STRENGTH, F_SCORE_WEIGHT, F_LIMIT, F_COV_FLOOR = range(len(FLOATS))
# the several-target kernel's "scene_ints" and "scene_floats" (empty for one target)
SCENE_INTS = ("max_targets", "extra_min", "keep_best")
S_MAX_TARGETS, S_EXTRA_MIN, S_KEEP_BEST = range(len(SCENE_INTS))
SCENE_FLOATS = (
    "max_cost", "share_penalty", "missing_shift", "share_tol", "min_separation", "double_tol",
)  # fmt: skip
S_MAX_COST, S_SHARE_PENALTY, S_MISSING_SHIFT, S_SHARE_TOL, S_MIN_SEPARATION, S_DOUBLE_TOL = range(
    len(SCENE_FLOATS)
)
# the front kernel's settings ("front_ints", "front_floats")
FRONT_INTS = ("blind_zone", "rf", "half_width", "max_iterations", "split", "toa_code")
FI_BLIND, FI_RF, FI_HALF_WIDTH, FI_MAX_ITER, FI_SPLIT, FI_TOA = range(len(FRONT_INTS))
FRONT_FLOATS = (
    "carrier", "threshold_hi", "threshold_lo", "min_amplitude", "mu_window", "split_min_sigma",
    "split_max_ratio",
)  # fmt: skip
FF_CARRIER, FF_HI, FF_LO, FF_MIN_AMP, FF_MU_WINDOW, FF_SPLIT_SIGMA, FF_SPLIT_RATIO = range(
    len(FRONT_FLOATS)
)
# the association MLP's weights and the ToA correction's trees, in their kernels' order, and
# what stands in for them without a prior (PRIOR_NONE) or trees (TIMING_NONE, TIMING_REFINE)
MLP, TREES = WEIGHTS, DENSE
_NO_MLP = {name: np.zeros((1,) * (2 if name[0] == "w" else 1), F32) for name in MLP}
_NO_TREES = dict(zip(TREES, (np.zeros((1, 1), I64), *np.zeros((2, 1, 1), F32), 0.0), strict=True))

_V, _M = ("n",), ("n", "n")  # a vector, a matrix (their sizes given by the pipeline)
CONSTANTS = Table(
    (
        Field("floats", F64, _V),
        Field("quality", F64, _V),
        Field("assoc_delays", F64, _V),
        Field("listening", FLAGS, _V),
        Field("max_path_diff", F64, _M),
        Field("anchors", I64, _M),
        Field("cost_weights", F64, _V),
        Field("delays", F64, _V),
        Field("channels", F64, _M),
        Field("emitter", F64, _V),
        Field("facing", F64, _V),
        *(Field(name, F32, _M if name[0] == "w" else _V) for name in MLP),
        Field("feature", I64, _M),
        Field("threshold", F32, _M),
        Field("value", F32, _M),
        Field("base", F64, ()),
        Field("scene_ints", I64, _V),
        Field("scene_floats", F64, _V),
        Field("share_listening", FLAGS, _V),
        Field("front_ints", I64, _V),
        Field("front_floats", F64, _V),
    ),
    BUFFERS,
)
(
    L_FLOATS, L_QUALITY, L_ASSOC_DELAYS, L_LISTENING, L_MAX_PATH_DIFF, L_ANCHORS,
    L_COST_WEIGHTS, L_DELAYS, L_CHANNELS, L_EMITTER, L_FACING, L_MEAN, L_STD, L_W0, L_B0, L_W1,
    L_B1, L_W2, L_B2, L_WH, L_BH, L_FEATURE, L_THRESHOLD, L_VALUE, L_BASE, L_SCENE_INTS,
    L_SCENE_FLOATS, L_SHARE_LISTENING, L_FRONT_INTS, L_FRONT_FLOATS,
) = range(len(CONSTANTS))  # fmt: skip


class KernelConfig(NamedTuple):
    """The constant arguments of both acquisition kernels, in their order."""

    ints: np.ndarray
    f64: np.ndarray
    f32: np.ndarray
    i64: np.ndarray
    flags: np.ndarray
    layout: np.ndarray


def kernel_config(pipeline) -> KernelConfig | None:
    """The kernels' constants for ``pipeline`` (a staged Pipeline), or None when it has a
    step without a compiled form (``Pipeline.kernel_constants`` is None) or a constant of
    another dtype than its field's: then the staged path runs. Values are never converted."""
    values = pipeline.kernel_constants()
    if values is None:
        return None
    values = {**_NO_MLP, **_NO_TREES, **front_constants(pipeline.profile), **values}
    several = values["max_targets"] > 1
    arrays = {name: values[name] for name in CONSTANTS.names() if name in values}
    arrays["floats"] = np.array([values[name] for name in FLOATS], dtype=np.float64)
    arrays["scene_ints"] = np.array(
        [values[name] for name in SCENE_INTS] if several else [], dtype=np.int64
    )
    arrays["scene_floats"] = np.array(
        [values[name] for name in SCENE_FLOATS] if several else [], dtype=np.float64
    )
    if not several:
        arrays["share_listening"] = np.zeros(0, np.bool_)
    arrays["front_ints"] = np.array([int(values[name]) for name in FRONT_INTS], dtype=np.int64)
    arrays["front_floats"] = np.array([values[name] for name in FRONT_FLOATS], dtype=np.float64)
    ints = dict(values, prior=PRIORS.index(values["prior"]), timing=TIMINGS.index(values["timing"]))
    packed = CONSTANTS.pack(arrays)
    if packed is None:
        log.debug("compiled path off: a constant is not of its field's dtype")
        return None
    (f64, f32, i64, flags), layout = packed
    return KernelConfig(
        np.array([ints[name] for name in INTS], dtype=np.int64), f64, f32, i64, flags, layout
    )


def front_constants(profile) -> dict:
    """The front kernel's settings (:data:`FRONT_INTS`, :data:`FRONT_FLOATS`) from a profile,
    as the staged stages read them."""
    acq, d, m = profile.acquisition, profile.detect, profile.memg
    cycles_per_sample = acq.carrier_hz / acq.sample_rate_hz
    return {
        "blind_zone": int(profile.preprocess.blind_zone_samples),
        "rf": acq.signal == "rf",
        "carrier": float(cycles_per_sample),
        "half_width": max(1, int(round(0.5 / cycles_per_sample))),  # as envelope()
        "threshold_hi": float(d.threshold),
        "threshold_lo": float(d.threshold * d.hysteresis),
        "min_amplitude": float(d.min_amplitude),
        "mu_window": float(m.mu_window),
        "max_iterations": int(m.max_iterations),
        "split": bool(m.split_merged),
        "split_min_sigma": float(m.split_min_sigma),
        "split_max_ratio": float(m.split_max_cost_ratio),
        "toa_code": TOA_CODES[m.toa],
    }


@jit(inline="always")
def view_1d(buf, layout, slot):
    o = layout[3 * slot]
    return buf[o : o + layout[3 * slot + 1]]


@jit(inline="always")
def view_2d(buf, layout, slot):
    o, d0, d1 = layout[3 * slot], layout[3 * slot + 1], layout[3 * slot + 2]
    return buf[o : o + d0 * d1].reshape((d0, d1))


@jit(inline="always")
def back_views(f64, f32, i64, flags, layout):
    """The constants from "floats" to "base", in the order of the back steps' parameters
    (``one_target._back_steps``, ``several_targets._scene_steps``)."""
    return (
        view_1d(f64, layout, L_FLOATS), view_1d(f64, layout, L_QUALITY),
        view_1d(f64, layout, L_ASSOC_DELAYS), view_1d(flags, layout, L_LISTENING),
        view_2d(f64, layout, L_MAX_PATH_DIFF), view_2d(i64, layout, L_ANCHORS),
        view_1d(f64, layout, L_COST_WEIGHTS), view_1d(f64, layout, L_DELAYS),
        view_2d(f64, layout, L_CHANNELS), view_1d(f64, layout, L_EMITTER), view_1d(f64, layout, L_FACING),
        view_1d(f32, layout, L_MEAN), view_1d(f32, layout, L_STD), view_2d(f32, layout, L_W0),
        view_1d(f32, layout, L_B0), view_2d(f32, layout, L_W1), view_1d(f32, layout, L_B1),
        view_2d(f32, layout, L_W2), view_1d(f32, layout, L_B2), view_2d(f32, layout, L_WH),
        view_1d(f32, layout, L_BH), view_2d(i64, layout, L_FEATURE), view_2d(f32, layout, L_THRESHOLD),
        view_2d(f32, layout, L_VALUE), f64[layout[3 * L_BASE]],
    )  # fmt: skip


@jit(inline="always")
def scene_views(f64, i64, flags, layout):
    """ "scene_ints", "scene_floats", "share_listening" (empty for one target)."""
    return (
        view_1d(i64, layout, L_SCENE_INTS),
        view_1d(f64, layout, L_SCENE_FLOATS),
        view_1d(flags, layout, L_SHARE_LISTENING),
    )


@jit(inline="always")
def front_views(f64, i64, layout):
    """ "front_ints", "front_floats": the front kernel's settings."""
    return view_1d(i64, layout, L_FRONT_INTS), view_1d(f64, layout, L_FRONT_FLOATS)
