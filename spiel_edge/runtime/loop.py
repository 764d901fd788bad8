"""The live loop: acquisitions from a device session through the pipeline into a sink.

One record per acquisition, the replay record plus ``seq`` (record counter), ``acquisition``
(the board's index), ``device_time_us``, ``host_time`` (Unix seconds when its last byte was
read) and ``truth_mm`` when the board knows the ground truth (the virtual board).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spiel_edge.board_config.profile_choice import run_profile
from spiel_edge.device import DeviceSession, LiveAcquisition
from spiel_edge.errors import ConfigError, DeviceError, InputError, SpielError
from spiel_edge.outputs import Sink
from spiel_edge.outputs.sink import HOLD
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.runtime.once import OncePerProblem
from spiel_edge.runtime.records import error_record
from spiel_edge.runtime.track_records import ResultTracker, track_records
from spiel_edge.safety.limits import load_npy_bounded

log = logging.getLogger(__name__)

LATENCY_WINDOW = 4096  # recent latencies kept for the status line
# interpreted kernels: the backlog kept (board time) before the oldest acquisitions are skipped
MAX_BEHIND_S = 1.0


@dataclass
class LiveStats:
    records: int = 0
    fixes: int = 0
    errors: int = 0  # acquisitions the pipeline rejected
    skipped: int = 0  # acquisitions dropped unprocessed: interpreted kernels behind the board
    started: float = field(default_factory=time.monotonic)
    latencies_us: deque[float] = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    all_latencies_us: list[float] = field(default_factory=list)  # kept when asked (benchmarks)
    cpu_at_first_s: float | None = None  # process CPU seconds when the first record was out

    def cpu_us_per_record(self) -> float | None:
        """CPU of this process per record after the first (start-up excluded; a virtual
        board in this process counts, one served from another process does not)."""
        if self.cpu_at_first_s is None or self.records < 2:
            return None
        return (time.process_time() - self.cpu_at_first_s) / (self.records - 1) * 1e6

    def median_latency_ms(self) -> float | None:
        return float(np.median(self.latencies_us)) / 1e3 if self.latencies_us else None


def load_background(path: str | Path) -> np.ndarray:
    """A target-free capture (channels, samples) from a .npy file or a spiel-csv frames file,
    told by the content."""
    path = Path(path)
    kind = None if path.suffix == ".npy" else _head_kind(path)
    if kind in ("npz", "mcap"):
        what = {"npz": "an .npz archive", "mcap": "an MCAP recording"}[kind]
        raise InputError(
            f"{path}: {what}; a background is a .npy capture (`spiel-edge background -o "
            "bg.npy`) or a spiel-csv frames file"
        )
    if path.suffix == ".npy" or kind == "npy":
        arr = load_npy_bounded(path, "background")  # header checked before the data is read
    else:
        from spiel_edge.recordings.spiel_csv import read_frames

        arr = read_frames(path)
    if arr.ndim != 2 or not np.all(np.isfinite(arr)):
        raise InputError(
            f"{path}: a background must be a finite (channels, samples) array, got shape {arr.shape}"
        )
    return arr.astype(np.float64)


def _head_kind(path: Path) -> str | None:
    """What a regular file's first bytes say it is (recordings/kinds.sniff); None for anything
    else, which the bounded readers refuse in their own words (a FIFO is never opened here)."""
    import os
    import stat

    from spiel_edge.recordings.kinds import sniff

    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        return sniff(path)
    except (OSError, InputError):
        return None


def warm_up(pipeline: Pipeline) -> None:
    """Run the pipeline once on a closed-form acquisition of the profile's shape (no simulator
    import), so numba's compilation or cache load happens before the stream starts."""
    from spiel_edge.runtime.warmup import closed_form_acquisition

    try:
        pipeline.process(*closed_form_acquisition(pipeline.profile))
    except SpielError as exc:  # an unusual profile: the live stream will tell
        log.debug("warm-up: %s", exc)


def open_pipeline(
    session: DeviceSession,
    profile_name: str,
    calibration: str | Path | None = None,
    association: str | None = None,
    *,
    use_board: bool = True,
    toa_correction: str | None = None,
    max_targets: int | None = None,
    chosen: bool = False,
    resolved=None,
    prepared: Pipeline | None = None,
) -> tuple[Pipeline, str]:
    """Open ``session``, choose the profile (``calibration`` > the board's stored config, unless
    ``use_board`` is false > ``profile_name``), build the pipeline (up to ``max_targets``
    targets) and warm it up. Returns the pipeline and where its geometry came from; closing
    the session is the caller's. ``toa_correction``: as :func:`live_toa_correction` chooses,
    or as given when the caller chose it already (``chosen``); ``resolved``: the profile and
    the calibrated one when the caller loaded them (board_config/profile_choice.run_profile);
    ``prepared``: the pipeline the caller built (and warmed up) for the second of them, used
    unless the board's stored config changes the profile."""
    if not chosen:
        toa_correction = live_toa_correction(session.url, toa_correction)
    session.open()
    profile, source = run_profile(
        session, profile_name, calibration, use_board=use_board, resolved=resolved
    )
    if prepared is not None and resolved is not None and profile is resolved[1]:
        return prepared, source  # the board left the profile as it was: built once
    pipeline = build_pipeline(profile, association, toa_correction)
    if max_targets:
        pipeline.set_max_targets(max_targets)
    warm_up(pipeline)
    return pipeline, source


def live_toa_correction(url: str, requested: str | None) -> str | None:
    """The learned ToA correction for a board: ``requested``, else none on a virtual board's
    modelled envelope (the correction was learned on the real board's), else None (the
    profile's)."""
    if requested is not None or not url.lower().startswith("sim:"):
        return requested  # a real board: the virtual board's modules are not even imported
    from spiel_edge.link.sim_options import modelled_envelope

    if modelled_envelope(url):
        log.info("virtual board with a modelled envelope: no learned ToA correction")
        return "none"
    return None


def check_stream_shape(session: DeviceSession, pipeline: Pipeline) -> None:
    """The board's stream must match the profile the pipeline was built for."""
    stream = session.stream
    p = pipeline.profile
    want = (p.geometry.n_channels, p.acquisition.n_samples)
    if stream is not None and (stream.n_channels, stream.n_samples) != want:
        raise ConfigError(
            f"the board streams {stream.n_channels} x {stream.n_samples} samples but profile "
            f"{p.name!r} expects {want[0]} x {want[1]}; use a matching --profile"
        )
    if stream is not None and abs(stream.sample_rate_hz - p.acquisition.sample_rate_hz) > 0.5:
        log.warning(
            "board samples at %d Hz, profile %r assumes %g Hz",
            stream.sample_rate_hz,
            p.name,
            p.acquisition.sample_rate_hz,
        )


def _stamp_fields(acq: LiveAcquisition) -> dict:
    """Protocol 2: the acquisition's board time on the host clock (Unix s) and its uncertainty."""
    stamp = getattr(acq, "stamp_host", None)
    if stamp is None:
        return {}
    return {
        "stamp_host": round(stamp, 6),
        "stamp_uncertainty_us": round(acq.stamp_uncertainty_us, 1),
        "stamp_source": getattr(acq, "stamp_source", None) or "board",
    }


def _stamp_phase_meta(acq: LiveAcquisition) -> dict:
    """Recorded beside the raw samples: the synced stamp and, from I/Q, the phase (rad)."""
    out = {}
    stamp = getattr(acq, "stamp_host", None)
    if stamp is not None:
        out["stamp_host_ns"] = int(stamp * 1e9)
    phase = getattr(acq, "phase", None)
    if phase is not None:
        out["phase"] = np.round(phase.astype(np.float64), 4).tolist()
    return out


class LiveRunner:
    def __init__(
        self,
        session: DeviceSession,
        pipeline: Pipeline,
        sink: Sink,
        *,
        background: np.ndarray | None = None,
        keep_latencies: bool = False,
        tracker: ResultTracker | None = None,
    ):
        self.session = session
        self.pipeline = pipeline
        self.sink = sink
        self.background = background  # fixed background; else the one the link sends, if any
        self.keep_latencies = keep_latencies
        self.tracker = tracker  # records gain ``tracks`` (runtime/track_records.py)
        self.on_record: Callable[[], None] | None = None  # e.g. the systemd watchdog ping
        self.on_acquisition: Callable[[LiveAcquisition], None] | None = None  # run --slot
        # what is done with each acquisition (None: its record written, ``handle``); a board
        # of ``run --robot`` reports its targets to the fusion instead (robot/board_worker.py)
        self.step: Callable[[LiveAcquisition], object] | None = None
        self.stats = LiveStats()
        self.tiers = None  # a runtime.tiered.TieredStart: interpreted kernels until compiled
        self._link_background: tuple[np.ndarray, np.ndarray] | None = None
        self._warned_no_background = False
        self.background_hint = "give --background FILE"  # what to do when none comes
        self.problems = OncePerProblem(log)
        sink.set_status_provider(self.diagnostics)  # ROS 2 sinks publish it on /diagnostics

    def run(
        self,
        stop: threading.Event,
        *,
        frames: int | None = None,
        status: Callable[[LiveRunner], None] | None = None,
        status_every_s: float = 2.0,
    ) -> LiveStats:
        """Process acquisitions until ``stop`` is set or ``frames`` records were written."""
        next_status = time.monotonic() + status_every_s
        holding = HOLD in self.sink.capabilities
        if holding:
            self.sink.batch()  # NDJSON flushed once the acquisitions read so far are all handled
        waiting = getattr(getattr(self.session, "tracker", None), "ready", ())
        step = self.step or self.handle
        for acq in self.session.acquisitions(stop):
            step(acq)
            if self.tiers is not None and self.tiers.is_interpreted:
                self._between_tiers()
            if self.on_acquisition is not None:
                self.on_acquisition(acq)
            if holding and not waiting:
                self.sink.flush()
            if frames is not None and self.stats.records >= frames:
                break
            if not self.sink.alive:  # a fan-out whose outputs all failed
                log.error("every output failed; stopping")
                break
            if status is not None and time.monotonic() >= next_status:
                self.refresh_device_counters()
                status(self)
                next_status = time.monotonic() + status_every_s
        if holding:
            self.sink.flush()  # what is held, before the caller closes: a failure shows here
        return self.stats

    def _between_tiers(self) -> None:
        """Interpreted kernels: switch when the compiled ones are ready, else keep to the
        newest acquisition (the ones skipped are counted)."""
        if not self.tiers.between():
            self.stats.skipped += self.session.newest_only(MAX_BEHIND_S)

    def handle(self, acq: LiveAcquisition) -> dict:
        record = self.record(acq)
        if self.sink.wants_acquisitions:  # recordings keep the raw samples and the background
            self.sink.write_acquisition(self._acquisition_meta(acq, record), acq.samples)
        self.sink.write(record)
        if self.stats.cpu_at_first_s is None:
            self.stats.cpu_at_first_s = time.process_time()
        if self.on_record is not None:
            self.on_record()
        latency_us = (time.perf_counter_ns() - acq.received_ns) / 1e3
        self.stats.latencies_us.append(latency_us)
        if self.keep_latencies:
            self.stats.all_latencies_us.append(latency_us)
        return record

    def _acquisition_meta(self, acq: LiveAcquisition, record: dict) -> dict:
        background = self.background if self.background is not None else acq.background
        return {
            "seq": record["seq"],
            "acquisition": acq.index,
            "device_time_us": acq.timestamp_us,
            "timestamp_ns": int(acq.host_time * 1e9),
            "background": background,
            **_stamp_phase_meta(acq),
            **_truth_meta(acq),
        }

    def record(self, acq: LiveAcquisition) -> dict:
        stats = self.stats
        head = {
            "seq": stats.records,
            "acquisition": acq.index,
            "device_time_us": acq.timestamp_us,
            "host_time": round(acq.host_time, 6),
            "source": self.session.url,
            **_stamp_fields(acq),
        }
        stats.records += 1
        result, error = self.process(acq)
        if result is None:
            record = {**head, **error_record(error)}
            tracks = self._track(None, acq)
        else:
            stats.fixes += result.position_mm is not None
            tracks = self._track(result, acq)
            record = {**head, **result.record()}
        if tracks is not None:
            record["tracks"] = tracks
        if acq.truth_mm is not None:
            record["truth_mm"] = [round(v, 2) for v in acq.truth_mm.tolist()]
        truths = acq.truth_targets_mm
        if truths is not None:
            record["truth_targets_mm"] = [[round(v, 2) for v in p] for p in truths.tolist()]
        if self.tiers is not None and self.tiers.is_interpreted:
            record["tier"] = "interpreted"  # the same values; compiled records carry no tier
        return record

    def process(self, acq: LiveAcquisition):
        """The pipeline's result for one acquisition, and None; or None and why the pipeline
        rejected it (counted, logged once per kind of problem)."""
        try:
            # an I/Q profile's ranging pipeline takes the pairs themselves (their phase times
            # the echo: pipeline/ranging.py); every other pipeline the envelope
            takes_iq = acq.iq is not None and getattr(self.pipeline, "takes_iq", False)
            frames = acq.iq if takes_iq else acq.samples
            return self.pipeline.process(frames.astype(np.float64), self._background_for(acq)), None
        except SpielError as exc:
            self.stats.errors += 1
            self.problems.log(str(exc), f"first at acquisition {acq.index} of {self.session.url}")
            return None, str(exc)

    def _track(self, result, acq: LiveAcquisition) -> list[dict] | None:
        """Track on the board's clock (sets the result's targets' track ids)."""
        if self.tracker is None:
            return None
        captured = (
            self.background is not None or acq.background is not None
        ) and self.pipeline.profile.preprocess.background_subtraction
        return track_records(self.tracker.update(result, acq.timestamp_us / 1e6, captured))

    def _background_for(self, acq: LiveAcquisition) -> np.ndarray | None:
        if self.background is not None:
            return self.background
        if acq.background is None:
            if (
                not self._warned_no_background
                and self.pipeline.profile.preprocess.background_subtraction
            ):
                log.warning(
                    "no background capture: positions will be poor; %s", self.background_hint
                )
                self._warned_no_background = True
            return None
        cached = self._link_background
        if cached is None or cached[0] is not acq.background:  # convert each new one once
            cached = self._link_background = (acq.background, acq.background.astype(np.float64))
        return cached[1]

    def refresh_device_counters(self) -> None:
        """Ask the board for its counters (overruns); a failure is left to the stream loop."""
        try:
            self.session.stream_status()
        except DeviceError as exc:
            log.debug("stream status: %s", exc)

    def diagnostics(self) -> dict:
        """The session's counters and the board's state, for diagnostic_msgs/DiagnosticStatus:
        level 0 OK, 1 WARN (acquisitions lost, damaged or rejected so far, or the link was
        lost and came back), 2 ERROR (waiting for the board)."""
        s, c = self.stats, self.session.counts()
        hello = getattr(self.session, "hello", None)
        serial = str(getattr(hello, "serial", "") or "") if hello is not None else ""
        waiting = c.get("disconnects", 0) > c.get("reconnects", 0)
        trouble = any(c.get(k, 0) for k in ("lost", "damaged", "crc_errors", "overruns"))
        level = 2 if waiting else 1 if trouble or s.errors or c.get("disconnects", 0) else 0
        message = (
            "waiting for the board"
            if waiting
            else "acquisitions lost or damaged"
            if trouble
            else "streaming"
        )
        values = {
            "port": self.session.url,
            "records": s.records,
            "fixes": s.fixes,
            "rejected": s.errors,
            **c,
        }
        if self.tiers is not None:
            values["kernels"] = self.tiers.status_text()
            values["skipped"] = s.skipped
        if hello is not None:
            values["firmware"] = getattr(hello, "firmware_version", "")
        return {
            "name": "spiel-edge: ultrasonic array",
            "hardware_id": serial or self.session.url,
            "level": level,
            "message": message,
            "values": values,
        }

    # --- text for people -----------------------------------------------------------------

    def status_line(self) -> str:
        s, c = self.stats, self.session.counts()
        elapsed = max(time.monotonic() - s.started, 1e-9)
        fixes = 100.0 * s.fixes / s.records if s.records else 0.0
        latency = s.median_latency_ms()
        lat = "-" if latency is None else f"{latency:.2f} ms"
        return (
            f"{s.records} records {s.records / elapsed:.1f}/s  fixes {fixes:.0f}%  "
            f"lost {c['lost']} (damaged {c['damaged']}, overruns {c['overruns']})  "
            f"reconnects {c['reconnects']}  latency {lat}"
            + (f"  skipped {s.skipped}" if s.skipped else "")
            + (f"  {self.tiers.status_text()}" if self._tier_shown() else "")
        )

    def _tier_shown(self) -> bool:
        return self.tiers is not None and (self.tiers.is_interpreted or bool(self.tiers.rounds))

    def summary(self) -> str:
        s = self.stats
        elapsed = time.monotonic() - s.started
        c = self.session.counts()
        lat = np.array(s.latencies_us) / 1e3
        latency = (
            f"latency median {np.median(lat):.2f} ms, p95 {np.percentile(lat, 95):.2f} ms"
            if lat.size
            else "no latency"
        )
        errors = f", {s.errors} rejected" if s.errors else ""
        if s.skipped:
            errors += f", {s.skipped} skipped (interpreted kernels behind the board)"
        if self.tiers is not None and self.tiers.rounds:
            errors += f"; {self.tiers.status_text()}"
        counters = ", ".join(f"{k} {v}" for k, v in c.items() if v and k != "acquisitions")
        cpu = s.cpu_us_per_record()
        cpu_text = f"; CPU {cpu:.0f} us per record" if cpu is not None else ""
        return (
            f"{s.records} records in {elapsed:.1f} s, {s.fixes} fixes{errors}; {latency}"
            + cpu_text
            + (f"; {counters}" if counters else "")
        )


def _truth_meta(acq: LiveAcquisition) -> dict:
    """The ground truth a virtual board sent, kept in the recording so a replay keeps it."""
    truth = getattr(acq, "truth_mm", None)
    return {} if truth is None else {"truth_mm": [round(float(v), 2) for v in truth]}
