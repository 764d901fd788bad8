"""From decoded stream frames to whole acquisitions, with the counters the session reports.

Pure (no I/O): the session feeds it frames with the time their bytes were read. Channel
frames go through firmware_protocol's AcquisitionAssembler; annotations (ground truth and
scene background from a virtual board) are attached to the acquisition they name.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from spiel_edge.device.annotation import ANNOTATION_TYPE, TARGETS_TYPE, Annotation, TruthTargets
from spiel_edge.device.iq import iq_amplitude, iq_phase
from spiel_edge.device.sanity import StreamSanity
from spiel_edge.protocol import AcquisitionAssembler, MessageError, MsgType, SampleFormat
from spiel_edge.protocol.framing import Frame

log = logging.getLogger(__name__)

_MASK = 0xFFFFFFFF
MAX_PENDING_TRUTH = 256
MAX_INDEX_GAP = 1 << 16  # acquisitions; a larger jump is a reset or corrupt index, not loss
LOST_BURST = 20  # this many acquisitions lost at once are said, not only counted


@dataclass(frozen=True)
class LiveAcquisition:
    """One acquisition from the board, as it arrived."""

    index: int  # the board's acquisition index (restarts when the board reboots)
    timestamp_us: int  # board clock at the first sample
    sample_rate_hz: int
    samples: np.ndarray  # (channels, samples), the wire dtype (uint16 envelope)
    received_ns: int  # time.perf_counter_ns() when its last byte was read
    host_time: float  # time.time() when it was assembled: after received_ns, not a pair with it
    truth_mm: np.ndarray | None = None  # ground truth, when a virtual board sends it
    background: np.ndarray | None = None  # latest target-free scene the link sent, if any
    truth_targets_mm: np.ndarray | None = None  # (K, 3) every target's truth, when sent
    # protocol version 2: the acquisition's board time on the host's clock (Unix s) and its
    # uncertainty (us, about 95 %), None before the clocks are synced or from a v1 board
    stamp_host: float | None = None
    stamp_uncertainty_us: float | None = None
    iq: np.ndarray | None = None  # I/Q streams: the raw (channels, 2 x samples) int16 q, i
    # "board": stamp_host is the board's clock mapped by TIME_SYNC; "arrival": the board's
    # clock could not be trusted and stamp_host is the host's arrival time (wider uncertainty)
    stamp_source: str | None = None

    @property
    def phase(self) -> np.ndarray | None:
        """I/Q streams: the phase (channels, samples) in radians, float32 (else None)."""
        return None if self.iq is None else iq_phase(self.iq)


class StreamAssembly:
    """Feeds stream frames to the assembler; counts lost acquisitions by index gaps."""

    def __init__(self) -> None:
        self.assembler = AcquisitionAssembler()
        self.ready: deque[LiveAcquisition] = deque()
        self.acquisitions = 0  # delivered to the caller (pop), not merely assembled
        self.lost = 0  # acquisition indices never delivered (damaged, dropped, overrun)
        self.jumps = 0  # index jumps too large to be losses (counted here, not in lost)
        self.bad_messages = 0  # frames with a valid CRC whose payload did not decode
        self.background: np.ndarray | None = None
        self._last_index: int | None = None
        self._truth: dict[int, np.ndarray] = {}
        self._truth_targets: dict[int, np.ndarray] = {}
        self._rows: dict[int, np.ndarray] = {}
        self._rows_for = -1
        self._first_delivered: int | None = None
        # (board time us, arrival perf ns, span us) -> (Unix s, uncertainty us, source) or
        # None; set by the session
        self.stamp: Callable[[int, int, float], tuple[float, float, str] | None] = (
            lambda board_us, received_ns, span_us: None
        )
        self.sanity = StreamSanity()  # a lying firmware: checked frame by frame
        self.progress_at = time.monotonic()  # the last acquisition assembled (or stream begun)
        self.frame_at = time.monotonic()  # the last stream frame
        self.frames_since = 0  # stream frames since the last acquisition assembled

    def begin(self, channel_mask: int = 0) -> None:
        """A new stream is being requested: forget the old one's leftovers. Its first
        frames may arrive before the answer (when the answer was lost and retried).
        ``channel_mask``: a channel subset under protocol version 2 (physical ids)."""
        self.assembler.reset(channel_mask)
        self.ready.clear()
        self._truth.clear()
        self._truth_targets.clear()
        self._last_index = None
        self._first_delivered: int | None = None
        self.sanity.n_channels = None  # until the board's answer says what to expect
        self.progress_at = self.frame_at = time.monotonic()
        self.frames_since = 0

    def pop(self) -> LiveAcquisition:
        """The next ready acquisition, counted as delivered."""
        acq = self.ready.popleft()
        self.acquisitions += 1
        return acq

    def _count_gap(self, gap: int) -> None:
        if gap > MAX_INDEX_GAP:
            self.jumps += 1
            return
        self.lost += gap
        if gap >= LOST_BURST:  # counters alone would hide a freeze of the board or the link
            log.warning(
                "%d acquisitions lost in a row (the board froze, or the link dropped them)", gap
            )

    def started(self, first_acquisition: int) -> None:
        """The board's answer: the stream began at ``first_acquisition``."""
        if self._first_delivered is None:
            self._last_index = (first_acquisition - 1) & _MASK
        else:
            self._count_gap((self._first_delivered - first_acquisition) & _MASK)

    def stop(self) -> None:
        """The stream ended or the link was lost: a partial acquisition is incomplete."""
        self.assembler.flush()
        self.assembler.reset()
        self._last_index = None

    def feed(self, frame: Frame, received_ns: int) -> bool:
        """Handle a stream or annotation frame; False if it is neither."""
        if frame.msg_type == MsgType.STREAM_DATA and not frame.is_response:
            self._stream_data(frame, received_ns)
            return True
        if frame.msg_type == ANNOTATION_TYPE and not frame.is_response:
            self._annotation(frame)
            return True
        if frame.msg_type == TARGETS_TYPE and not frame.is_response:
            self._targets_annotation(frame)
            return True
        return False

    def _stream_data(self, frame: Frame, received_ns: int) -> None:
        self.frame_at = time.monotonic()
        self.frames_since += 1
        self.sanity.payload(frame.payload, frame.aux)  # FirmwareError: the stream contradicts
        try:  # straight from the payload into the acquisition's array (no StreamData)
            acq = self.assembler.feed_payload(frame.payload, frame.aux)
        except MessageError as exc:
            self.bad_messages += 1
            log.debug("bad STREAM_DATA: %s", exc)
            return
        if acq is None:
            return
        self.progress_at, self.frames_since = self.frame_at, 0
        if self._last_index is not None:
            gap = (acq.index - self._last_index - 1) & _MASK
            if gap < (1 << 31):
                self._count_gap(gap)
        elif self._first_delivered is None:
            self._first_delivered = acq.index
        self._last_index = acq.index
        samples, iq = acq.samples, None
        if acq.sample_format == SampleFormat.I16_IQ:
            samples, iq = iq_amplitude(acq.samples), acq.samples
        span_us = acq.samples.shape[-1] / max(acq.sample_rate_hz, 1) * 1e6
        stamped = self.stamp(acq.timestamp_us, received_ns, span_us)
        self.ready.append(
            LiveAcquisition(
                acq.index,
                acq.timestamp_us,
                acq.sample_rate_hz,
                samples,
                received_ns,
                time.time(),
                self._truth_for(acq.index),
                self.background,
                self._truth_targets.pop(acq.index, None),
                None if stamped is None else stamped[0],
                None if stamped is None else stamped[1],
                iq,
                None if stamped is None else stamped[2],
            )
        )
        if len(self._truth_targets) > MAX_PENDING_TRUTH:
            self._truth_targets.clear()

    def _truth_for(self, index: int) -> np.ndarray | None:
        truth = self._truth.pop(index, None)
        if len(self._truth) > MAX_PENDING_TRUTH:  # annotations whose acquisition never came
            self._truth.clear()
        return truth

    def _targets_annotation(self, frame: Frame) -> None:
        try:
            positions = TruthTargets.unpack(frame.payload)
        except MessageError:
            self.bad_messages += 1
            return
        truth = positions.positions_mm()
        if truth is None:
            self.bad_messages += 1
            return
        self._truth_targets[positions.acquisition] = truth

    def _annotation(self, frame: Frame) -> None:
        try:
            note = Annotation.unpack(frame.payload)
        except MessageError:
            self.bad_messages += 1
            return
        truth = note.truth_mm
        if truth is not None:
            self._truth[note.acquisition] = truth
        if not note.n_channels:
            return
        if note.acquisition != self._rows_for:
            self._rows, self._rows_for = {}, note.acquisition
        rows = note.background_rows()
        if not len(rows):
            self.bad_messages += 1  # rows that do not divide into n_samples
            return
        for offset, row in enumerate(rows):
            self._rows[note.first_channel + offset] = row
        if len(self._rows) == note.n_channels and set(self._rows) == set(range(note.n_channels)):
            rows, self._rows = [self._rows[c] for c in range(note.n_channels)], {}
            if len({len(r) for r in rows}) != 1:
                self.bad_messages += 1
                return
            self.background = np.stack(rows)
