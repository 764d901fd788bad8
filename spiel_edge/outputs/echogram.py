"""A live echogram: a waterfall of the A-scans with the detected echoes marked, as an RGB
image (rows: acquisitions, newest on top; columns: the channels' samples side by side).

Pure numpy (the Foxglove sink sends it as foxglove.RawImage on ``/spiel/echogram``). Each
channel's envelope, background subtracted and clipped at 0, is grey scaled by the largest value
seen on that channel so far; every echo of the record is a red pixel at its sample, the matched
one green; one blue column separates the channels.
"""

from __future__ import annotations

import numpy as np

ROWS = 128
ECHO_RGB = (255, 0, 0)
MATCH_RGB = (0, 255, 0)
SEPARATOR_RGB = (0, 0, 160)


class Echogram:
    def __init__(self, rows: int = ROWS) -> None:
        self.rows = rows
        self.image: np.ndarray | None = None  # (rows, width, 3) uint8
        self._peak: np.ndarray | None = None  # per channel, the largest envelope value so far

    def add(
        self,
        frames: np.ndarray,
        background: np.ndarray | None,
        echoes: list[list[float]],
        matched: list[int | None] | None = None,
    ) -> np.ndarray:
        """Push one acquisition's row on top; returns the whole image."""
        y = np.asarray(frames, dtype=np.float64)
        if background is not None and np.shape(background) == y.shape:
            y = np.clip(y - np.asarray(background, dtype=np.float64), 0.0, None)
        y = np.nan_to_num(y, nan=0.0, posinf=0.0, neginf=0.0)
        n_ch, n_t = y.shape
        width = n_ch * n_t + n_ch - 1
        if self.image is None or self.image.shape[1] != width:
            self.image = np.zeros((self.rows, width, 3), dtype=np.uint8)
            self._peak = np.zeros(n_ch)
        self._peak = np.maximum(self._peak, y.max(axis=1))
        scale = np.where(self._peak > 0, 255.0 / np.where(self._peak > 0, self._peak, 1.0), 0.0)
        row = np.zeros((width, 3), dtype=np.uint8)
        for ch in range(n_ch):
            start = ch * (n_t + 1)
            row[start : start + n_t] = np.clip(y[ch] * scale[ch], 0, 255).astype(np.uint8)[:, None]
            if ch + 1 < n_ch:
                row[start + n_t] = SEPARATOR_RGB
            for k, toa in enumerate(echoes[ch] if ch < len(echoes) else []):
                if toa is None or not np.isfinite(toa) or not 0 <= toa < n_t:
                    continue
                hit = matched is not None and ch < len(matched) and matched[ch] == k
                row[self.column(ch, toa, n_t)] = MATCH_RGB if hit else ECHO_RGB
        self.image = np.roll(self.image, 1, axis=0)
        self.image[0] = row
        return self.image

    @staticmethod
    def column(channel: int, sample: float, n_samples: int) -> int:
        """The image column of ``sample`` on ``channel``."""
        return channel * (n_samples + 1) + min(int(round(sample)), n_samples - 1)
