"""How the virtual board acquires and sends one acquisition: the scene's frame, its
annotations (ground truth, background), then one STREAM_DATA frame per channel, envelope or
(protocol 2) I/Q pairs, stamped with the board's own clock. Mixed into VirtualBoard."""

from __future__ import annotations

import numpy as np

from spiel_edge.device.annotation import encode_annotations, encode_truth_targets
from spiel_edge.protocol import Flags, SampleFormat, StreamData, encode_message
from spiel_edge.sim.faults import Outgoing

_MASK = 0xFFFFFFFF


class AcquireMixin:
    def _acquire(self, s) -> list[Outgoing]:
        index, time_s = self._acquisition, s.next_time - self._boot_time
        iq = s.sample_format == SampleFormat.I16_IQ
        frame = (
            self.scene.frame(index, s.n_samples, time_s, iq=True)
            if iq
            else (self.scene.frame(index, s.n_samples, time_s))
        )
        background = frame.background
        if (
            background is not None
            and self._last_background is not None
            and np.array_equal(background, self._last_background)
        ):
            background = None  # unchanged: the host keeps the one it has
        elif background is not None:
            self._last_background = background
        out = [
            Outgoing(w, exempt=True) for w in encode_annotations(index, frame.truth_mm, background)
        ]
        if frame.truth_targets_mm is not None:
            out.append(Outgoing(encode_truth_targets(index, frame.truth_targets_mm), exempt=True))
        channels = s.channels or tuple(range(frame.samples.shape[0]))
        n_ch = len(channels)
        if iq:
            rows = np.ascontiguousarray(frame.iq, dtype="<i2")  # (channels, samples, 2): q, i
        else:
            rows = np.ascontiguousarray(frame.samples, dtype="<u2")
        stamp = self.clock_us(s.next_time)
        for rank, c in enumerate(channels):
            msg = StreamData(
                index,
                c if self.version >= 2 else rank,  # v2: the physical channel id
                n_ch,
                s.sample_format,
                self.scene.sample_rate_hz,
                stamp,
                rows[c].tobytes(),
            )
            more = Flags.MORE if rank < n_ch - 1 else 0
            out.append(
                Outgoing(
                    encode_message(msg, seq=s.seq, flags=more, aux=self._counter), acquisition=index
                )
            )
            self._counter = (self._counter + 1) & _MASK
        self._acquisition = (index + 1) & _MASK
        self.stats.acquisitions_sent += 1
        self.stats.frames_sent += n_ch
        return out
