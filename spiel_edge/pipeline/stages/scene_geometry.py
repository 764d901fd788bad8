"""The scene stage's small geometric sums, compiled, for the staged and the fused path alike.

The after-locating checks (docs/scene.md: shared echoes, the minimum separation, double
reflections) compare lengths against tolerances. ``np.dot`` / ``np.linalg.norm`` of a
3-vector go through BLAS, whose rounding (fused multiply-add or not, summation order) depends
on the BLAS build and the CPU; these kernels sum in one fixed order instead, so the staged
path (:mod:`spiel_edge.pipeline.stages.scene`, ``Pipeline._targets``) and the fused several-target
kernel (:mod:`spiel_edge.pipeline.compiled.several_targets`) compute the same bits on every machine.
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit


@jit
def dot3(a, b):
    """a . b of two 3-vectors, summed in index order."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@jit
def distance3(a, b):
    """|a - b| of two 3-vectors."""
    d0, d1, d2 = a[0] - b[0], a[1] - b[1], a[2] - b[2]
    return math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@jit
def height3(position, emitter, facing):
    """(position - emitter) . facing: the distance in front of the board plane."""
    return (
        (position[0] - emitter[0]) * facing[0]
        + (position[1] - emitter[1]) * facing[1]
        + (position[2] - emitter[2]) * facing[2]
    )


@jit
def predicted_paths_into(position, channels, emitter, out):
    """Echo path (mm) per channel of a point target into ``out``."""
    out_len = distance3(position, emitter)
    for c in range(channels.shape[0]):
        out[c] = out_len + distance3(position, channels[c])


@jit
def predicted_paths_kernel(position, channels, emitter):
    out = np.empty(channels.shape[0])
    predicted_paths_into(position, channels, emitter, out)
    return out
