"""Preallocated buffers for one acquisition shape, so the acquisition kernels allocate no
arrays for their intermediates (outputs handed to the caller are still fresh copies)."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from spiel_edge.pipeline.stages.features import N_FEATURES


@dataclass
class Workspace:
    """Intermediate arrays of the front kernel for (channels, samples, max_echoes)."""

    n_channels: int
    n_samples: int
    max_echoes: int
    envelope: np.ndarray = field(init=False, repr=False)  # (channels, samples) RF -> envelope
    background: np.ndarray = field(init=False, repr=False)
    cleaned: np.ndarray = field(init=False, repr=False)  # preprocessed envelope
    peaks: np.ndarray = field(init=False, repr=False)
    counts: np.ndarray = field(init=False, repr=False)
    params: np.ndarray = field(init=False, repr=False)
    iterations: np.ndarray = field(init=False, repr=False)
    unsorted: np.ndarray = field(init=False, repr=False)  # features in detection order
    features: np.ndarray = field(init=False, repr=False)  # features in ToA order
    # the back steps' (one_target.py; bonus and clean also several_targets.py)
    bonus: np.ndarray = field(init=False, repr=False)  # (channels, max_echoes) score prior, mm
    clean: np.ndarray = field(init=False, repr=False)  # echo timing's background-free envelope
    matched: np.ndarray = field(init=False, repr=False)
    picked: np.ndarray = field(init=False, repr=False)  # the matched echoes' ToA
    weights: np.ndarray = field(init=False, repr=False)
    shift: np.ndarray = field(init=False, repr=False)
    paths: np.ndarray = field(init=False, repr=False)
    use: np.ndarray = field(init=False, repr=False)
    position: np.ndarray = field(init=False, repr=False)
    covariance: np.ndarray = field(init=False, repr=False)
    front_buffers: tuple = field(init=False, repr=False)
    back_buffers: tuple = field(init=False, repr=False)
    scene: object = field(default=None, init=False, repr=False)  # several_targets.SceneBuffers

    def __post_init__(self) -> None:
        shape = (self.n_channels, self.n_samples)
        echoes = (self.n_channels, self.max_echoes)
        self.envelope = np.empty(shape)
        self.background = np.empty(shape)
        self.cleaned = np.empty(shape)
        self.peaks = np.empty(echoes, dtype=np.int64)
        self.counts = np.empty(self.n_channels, dtype=np.int64)
        self.params = np.empty(echoes + (4,))
        self.iterations = np.empty(echoes, dtype=np.int64)
        self.unsorted = np.empty(echoes + (N_FEATURES,))
        self.features = np.empty(echoes + (N_FEATURES,))
        self.bonus = np.empty(echoes)
        self.clean = np.empty(shape)
        self.matched = np.empty(self.n_channels, dtype=np.int64)
        self.picked = np.empty(self.n_channels)
        self.weights = np.empty(self.n_channels)
        self.shift = np.empty(self.n_channels)
        self.paths = np.empty(self.n_channels)
        self.use = np.empty(self.n_channels, dtype=np.bool_)
        self.position = np.empty(3)
        self.covariance = np.empty((3, 3))
        # the kernels' buffer arguments, in their order (built once: the calls are hot)
        self.front_buffers = (
            self.envelope,
            self.background,
            self.cleaned,
            self.peaks,
            self.counts,
            self.params,
            self.iterations,
            self.unsorted,
            self.features,
        )
        self.back_buffers = (
            self.bonus,
            self.matched,
            self.picked,
            self.weights,
            self.shift,
            self.paths,
            self.use,
            self.clean,
            self.position,
            self.covariance,
        )


class ThreadWorkspaces:
    """One Workspace per thread (the kernels release the GIL: threads must not share one)."""

    def __init__(self, n_channels: int, n_samples: int, max_echoes: int):
        self._dims = (n_channels, n_samples, max_echoes)
        self._local = threading.local()

    def get(self) -> Workspace:
        ws = getattr(self._local, "workspace", None)
        if ws is None:
            ws = self._local.workspace = Workspace(*self._dims)
        return ws
