"""``replay``/``evaluate --jobs N``: the files of a spiel-csv folder on N worker processes.

Workers come from a "forkserver" context (numba's threads and a forked parent do not mix);
each builds its pipeline once from a picklable :class:`PipelineRecipe` (the numba cache makes
that a load, not a compile) and replays tasks of consecutive files. Results come back in
file order, so the records are those of one job. With tracking a task holds whole recordings
(``<run>_<index>`` names, see :mod:`spiel_edge.runtime.track_records`) and a fresh tracker; the
parent shifts each task's track ids by the ids issued before it, as one tracker would have.

Workers ignore INT and HUP (the terminal sends them to the whole group): the parent decides.
Closing the iterator (a signal's stop, an error, the end) cancels what is queued and
terminates the workers.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import signal
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path

from spiel_edge.recordings.spiel_csv import read_recording
from spiel_edge.runtime.recorded import Replayed, format_of, replay
from spiel_edge.runtime.track_records import ResultTracker, replay_tracked, run_and_index
from spiel_edge.safety.limits import InputLimits

log = logging.getLogger(__name__)

MAX_TASK_FILES = 32  # per task: few enough to spread a small folder, many enough to amortise
POLL_S = 0.2  # how often the parent looks at its stop flag while it waits
LOOKAHEAD_TASKS = 8  # per job: how far this process runs ahead of a late task (memory)


@dataclass(frozen=True)
class PipelineRecipe:
    """What a worker needs to build the same pipeline as the command's."""

    profile_name: str | None = None
    calibration: str | None = None
    association: str | None = None
    toa_correction: str | None = None
    max_targets: int | None = None

    def build(self):
        from spiel_edge.pipeline.factory import build_pipeline
        from spiel_edge.profile.schema import resolve_profile

        profile = resolve_profile(self.profile_name, self.calibration)
        pipeline = build_pipeline(profile, self.association, self.toa_correction)
        if self.max_targets:
            pipeline.set_max_targets(self.max_targets)
        return pipeline


@dataclass(frozen=True)
class Task:
    files: tuple[Path, ...]
    background: str | None
    limits: InputLimits | None
    track: bool
    keep_frames: bool  # an MCAP output writes the frames again


def resolve_jobs(jobs: int) -> int:
    """``0`` means one job per CPU."""
    return jobs if jobs > 0 else (os.cpu_count() or 1)


def plan_tasks(files: Sequence[Path], jobs: int, track: bool) -> list[tuple[Path, ...]]:
    """Consecutive files in tasks of at most ``MAX_TASK_FILES`` (about four per job); with
    ``track`` whole recordings in recording order, a recording never split."""
    size = max(1, min(MAX_TASK_FILES, math.ceil(len(files) / (4 * jobs))))
    if not track:
        return [tuple(files[i : i + size]) for i in range(0, len(files), size)]
    runs: dict[str, list[Path]] = {}
    for path in files:
        runs.setdefault(run_and_index(path.name)[0], []).append(path)
    tasks: list[tuple[Path, ...]] = []
    current: list[Path] = []
    for run in sorted(runs):
        if current and len(current) + len(runs[run]) > size:
            tasks.append(tuple(current))
            current = []
        current.extend(runs[run])
    if current:
        tasks.append(tuple(current))
    return tasks


def replay_files(
    pipeline,
    recipe: PipelineRecipe,
    files: Sequence[Path],
    jobs: int,
    *,
    background: str | Path | None = None,
    limits: InputLimits | None = None,
    track: bool = False,
    keep_frames: bool = False,
    stopped: Callable[[], bool] = lambda: False,
    on_workers: Callable[[Callable[[], None]], None] | None = None,
) -> Iterator[Replayed]:
    """:func:`~spiel_edge.runtime.recorded.replay` (or ``replay_tracked``) over ``files`` with
    ``jobs`` processes, in the order one job gives; ends early once ``stopped()`` is true.

    This process is one of the jobs: with its ``pipeline`` (built from ``recipe``) it runs
    the tasks in order until a worker has started (imports, kernels from the cache: a second
    or more), then keeps the workers fed and runs the next task whenever the one due is not
    back yet; its own task ends between two files once ``stopped()`` is true.
    ``on_workers`` receives a callable that terminates the workers at once, for a caller
    that may end the process without closing this iterator (the signal watchdog)."""
    bg = None if background is None else str(background)
    tasks = [Task(t, bg, limits, track, keep_frames) for t in plan_tasks(files, jobs, track)]
    if len(tasks) < 2:  # nothing to share
        for task in tasks:
            yield from run_task(pipeline, task, stopped)[0]
        return
    workers = max(1, min(jobs - 1, len(tasks) - 1))
    pool = ProcessPoolExecutor(
        workers, multiprocessing.get_context("forkserver"), _init_worker, _init_args(recipe)
    )
    done: dict[int, tuple[list[Replayed], int]] = {}
    sent: dict[int, Future] = {}
    due = queued = ids_before = 0
    started = pool.submit(_started)  # no task waits on a worker that is still starting
    if on_workers is not None:
        on_workers(lambda: _terminate_workers(pool))
    try:
        while due < len(tasks):
            if stopped():
                return
            while started.done() and queued < len(tasks) and len(sent) < workers + 1:
                sent[queued] = pool.submit(_run_task, tasks[queued])
                queued += 1
            if due in sent and sent[due].done():
                done[due] = sent.pop(due).result()
            if due in done:
                items, issued = done.pop(due)
                for item in items:
                    _shift_track_ids(item, ids_before)
                    yield item
                ids_before += issued
                due += 1
            elif queued < len(tasks) and queued - due < LOOKAHEAD_TASKS * jobs:
                done[queued] = run_task(pipeline, tasks[queued], stopped)  # meanwhile, here
                queued += 1
            else:
                _wait(sent[due])
    finally:
        _stop_pool(pool)


def _wait(future: Future) -> None:
    wait([future], timeout=POLL_S)


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    processes = _terminate_workers(pool)
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.join(timeout=2.0)
        if process.is_alive():
            process.kill()
            process.join()


def _terminate_workers(pool: ProcessPoolExecutor) -> list:
    """SIGTERM to every worker still alive (they do not ignore it); no waiting."""
    processes = list((pool._processes or {}).values())  # no public way before Python 3.14
    for process in processes:
        if process.is_alive():
            process.terminate()
    return processes


def _shift_track_ids(item: Replayed, offset: int) -> None:
    if not offset or item.tracks is None:
        return
    for track in item.tracks:
        track["track_id"] += offset
    if item.result is not None:
        for target in item.result.targets:
            if target.track_id is not None:
                target.track_id += offset


# -- in the workers ---------------------------------------------------------------------------

_pipeline = None


def _init_args(recipe: PipelineRecipe) -> tuple:
    root = logging.getLogger()
    fmt = root.handlers[0].formatter._fmt if root.handlers and root.handlers[0].formatter else None
    return recipe, root.level, fmt


def _init_worker(recipe: PipelineRecipe, level: int, fmt: str | None) -> None:
    global _pipeline
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    logging.basicConfig(level=level, format=fmt or logging.BASIC_FORMAT, force=True)
    _pipeline = recipe.build()


def _started() -> bool:
    return True


def _run_task(task: Task) -> tuple[list[Replayed], int]:
    return run_task(_pipeline, task)


def run_task(
    pipeline, task: Task, stopped: Callable[[], bool] = lambda: False
) -> tuple[list[Replayed], int]:
    """A task's items and the track ids its tracker issued (0 without tracking); it ends
    early, between two files, once ``stopped()`` is true (the caller then drops it)."""
    recordings = _read_until_stopped(task, stopped)
    if task.track:
        tracker = ResultTracker(pipeline.profile.track, pipeline.profile.scene)
        items = list(replay_tracked(pipeline, recordings, tracker=tracker))
        issued = tracker.tracker.ids_issued
    else:
        items, issued = list(replay(pipeline, recordings)), 0
    if not task.keep_frames:
        for item in items:
            item.recording = None
    return items, issued


def _read_until_stopped(task: Task, stopped: Callable[[], bool]):
    for path in task.files:
        if stopped():
            return
        yield read_recording(path, task.background, task.limits)


def usable_jobs(jobs: int, path: str | Path, fmt: str | None, track: bool, profile) -> int:
    """The jobs a replay of ``path`` can use: one for an MCAP file (one recording), and one
    when tracking with a running background (its estimate carries over between recordings)."""
    jobs = resolve_jobs(jobs)
    is_folder = Path(path).is_dir() and format_of(Path(path), fmt) == "spiel-csv"
    if not is_folder or (track and profile.track.running_background_window > 0):
        return 1
    return jobs
