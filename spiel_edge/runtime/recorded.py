"""Replay recorded acquisitions through the same pipeline as live operation."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spiel_edge.errors import InputError, SpielError
from spiel_edge.pipeline.staged import Pipeline, Result
from spiel_edge.profile.specs import TOA_CORRECTIONS
from spiel_edge.recordings.spiel_csv import Recording, iter_recordings
from spiel_edge.runtime.records import error_record
from spiel_edge.safety.limits import InputLimits

log = logging.getLogger(__name__)

FORMATS = ("spiel-csv", "mcap", "labelled", "stof-chirp")


@dataclass
class Replayed:
    source: str
    result: Result | None
    error: str | None
    tracks: list[dict] | None = None  # with tracking (runtime/track_records.py)
    recording: Recording | None = None  # its frames, for outputs that keep them (MCAP)

    def record(self) -> dict:
        out = self._record()
        if self.tracks is not None:
            out["tracks"] = self.tracks
        return out

    def _record(self) -> dict:
        if self.result is None:
            return {"source": self.source, **error_record(str(self.error))}
        out = {"source": self.source, **self.result.record()}
        truth = None if self.recording is None else self.recording.truth_mm
        if truth is not None:  # kept from the input (a labelled set, a sim:// recording)
            out["truth_mm"] = [round(float(v), 2) for v in truth]
        return out


class ReplaySummary:
    """What a replay did, in one line for a person: acquisitions, fixes, targets, and the
    error against the ground truth where the recordings carry it."""

    def __init__(self) -> None:
        self.total = self.failed = self.fixes = self.targets = 0
        self.errors_mm: list[float] = []

    def add(self, item: Replayed) -> None:
        self.total += 1
        if item.result is None:
            self.failed += 1
            return
        self.targets += len(item.result.targets)
        pos = item.result.position_mm
        if pos is None:
            return
        self.fixes += 1
        truth = None if item.recording is None else item.recording.truth_mm
        if truth is not None:
            self.errors_mm.append(float(np.linalg.norm(np.asarray(pos) - truth)))

    def line(self) -> str:
        done = self.total - self.failed
        share = f" ({self.fixes / done:.0%})" if done else ""
        text = (
            f"replayed {self.total} acquisitions: {self.fixes} with a position{share}, "
            f"{self.targets} targets in all"
        )
        if self.errors_mm:
            errs = np.array(self.errors_mm)
            text += (
                f"; against truth_mm: mean {errs.mean():.1f} mm, median "
                f"{np.median(errs):.1f} mm over {errs.size} positions"
            )
        if self.failed:
            text += f"; {self.failed} failed"
        return text


def format_of(path: Path, fmt: str | None = None) -> str:
    """``fmt``, else told by the content: a SToF-Chirp sequence folder (``NN_envelope_frame.txt``
    files), else :mod:`spiel_edge.recordings.kinds`: a spiel-csv folder, an MCAP recording or a
    labelled .npz; one InputError line for anything else."""
    if fmt:
        return fmt
    from spiel_edge.recordings.kinds import recording_kind
    from spiel_edge.recordings.stof_chirp import is_sequence

    return "stof-chirp" if is_sequence(path) else recording_kind(path, FORMATS)


def iter_sources(
    path: str | Path,
    fmt: str | None = None,
    background: str | Path | None = None,
    limits: InputLimits | None = None,
    *,
    iq: bool = False,
) -> Iterator[Recording]:
    """Recordings from a spiel-csv folder, an MCAP file, a labelled .npz or a SToF-Chirp
    folder (format told by the content), each bounded by ``limits`` (the profile's frame shape)
    before it is parsed. ``iq``: SToF-Chirp frames from the I/Q files (the profile's signal is
    "iq")."""
    path = Path(path)
    fmt = format_of(path, fmt)
    if fmt == "spiel-csv":
        yield from iter_recordings(path, background, limits)
    elif fmt == "stof-chirp":
        yield from _stof_sources(path, background, limits, iq)
    elif fmt == "mcap":
        try:
            from spiel_edge.recordings.mcap_reader import iter_mcap_recordings
        except ImportError as exc:
            raise InputError(
                f"{path}: MCAP replay is not available in this install ({exc})"
            ) from exc
        yield from iter_mcap_recordings(path, limits)
    elif fmt == "labelled":
        from spiel_edge.recordings.labelled import load_labelled

        yield from load_labelled(path, limits).recordings(path.name)
    else:
        raise InputError(f"unknown format {fmt!r}; known: {', '.join(FORMATS)}")


def _stof_sources(path, background, limits, iq) -> Iterator[Recording]:
    """Every frame of a SToF-Chirp sequence folder (source "NN"), or of each sequence under a
    dataset folder (source "<sequence>/NN"), in order."""
    from spiel_edge.recordings.stof_chirp import iter_stof_recordings, sequence_folders

    if background is not None:
        raise InputError("--background: SToF-Chirp recordings have no background captures")
    sequences = sequence_folders(path)
    for seq in sequences:
        for rec in iter_stof_recordings(seq, iq, limits):
            if len(sequences) > 1:
                rec.source = f"{seq.relative_to(path).as_posix()}/{rec.source}"
            yield rec


def chosen_toa_correction(toa_correction: str | None) -> dict[str, str]:
    """The recording metadata that says a ToA correction other than the profile's was used
    (given, or none on a modelled envelope); {} for the profile's own, which a replay with
    another profile should not override."""
    return {} if toa_correction is None else {"toa_correction": toa_correction}


def recorded_toa_correction(path: str | Path, fmt: str | None = None) -> str | None:
    """The learned ToA correction an MCAP recording was made with when it was not the profile's
    (``run`` and ``replay`` write it in their metadata: :func:`chosen_toa_correction`), so that
    replaying it reproduces its records; None (the profile's) for other inputs and for
    recordings that do not say."""
    path = Path(path)
    if format_of(path, fmt) != "mcap" or not path.is_file():
        return None
    try:
        from spiel_edge.recordings.mcap_reader import recording_metadata
    except ImportError:
        return None  # MCAP replay itself says why it is unavailable
    recorded = recording_metadata(path).get("toa_correction")
    if recorded not in TOA_CORRECTIONS:
        return None
    log.info("%s: the learned ToA correction it was recorded with: %s", path, recorded)
    return recorded


def replay(pipeline: Pipeline, recordings: Iterator[Recording]) -> Iterator[Replayed]:
    """Process each recording; a bad one yields an error entry and the replay goes on."""
    for rec in recordings:
        if rec.error is not None:
            log.error("%s", rec.error)
            yield Replayed(rec.source, None, rec.error, recording=rec)
            continue
        try:
            result = pipeline.process(rec.frames, rec.background)
        except SpielError as exc:
            message = f"{rec.source}: {exc}"
            log.error("%s", message)
            yield Replayed(rec.source, None, message, recording=rec)
            continue
        yield Replayed(rec.source, result, None, recording=rec)
