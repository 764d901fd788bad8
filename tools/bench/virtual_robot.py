"""The virtual robot end to end, offline: simulated acquisitions (sim/robot.py) -> each
board's pipeline -> host side (clocks, cross-talk marking) -> fusion -> scores.

Used by tools/bench/robot_eval.py and tools/research/robot_board_view.py only (moved out of
the wheel from spiel_edge/robot/virtual_run.py)."""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import numpy as np

from spiel_edge.profile.schema import load_profile
from spiel_edge.robot.coast import CoastPolicy
from spiel_edge.robot.fusion import BaseTarget, BoardReport, Fuser, reports_targets
from spiel_edge.robot.schedule import CrosstalkMarker, Schedule
from spiel_edge.track import Tracker
from tools.bench import robot_score as score

GHOST_NEW_MM = 30.0  # a target this far from every target of the clean frame ...
GHOST_TRUTH_MM = 40.0  # ... and from every object is one the other board's pulse made


@dataclass
class RunFigures:
    acquisitions: int = 0
    audible: int = 0  # a foreign arrival >= AUDIBLE_COUNTS in the window
    ghost: int = 0  # acquisitions with a target made by another board's pulse
    marked: int = 0
    ghost_unmarked: int = 0  # ghosts the marking missed (reach the fusion)
    restarts: dict = field(default_factory=dict)
    board_errors: list = field(default_factory=list)
    board_tracked_errors: list = field(default_factory=list)  # each board's own tracker
    # like for like (score.paired_errors): per mover-cycle the fused track and the primary
    # board's own tracker, with `run`'s [track] and with the fused tracker's [track]
    paired: dict = field(default_factory=dict)
    tracked_errors: list = field(default_factory=list)
    tracked_errors_in_view: list = field(default_factory=list)  # movers some board faces
    crossings: dict = field(default_factory=dict)
    oracle: dict = field(default_factory=dict)  # the truth's association (score.oracle_records)
    cycles: int = 0
    covered: float = 0.0
    pipeline_s: float = 0.0
    fusion_s: float = 0.0
    truths: list = field(default_factory=list, repr=False)  # per fused record, base_link

    def summary(self) -> dict:
        n = max(self.acquisitions, 1)
        c = self.crossings
        tracked = c.get("kept", 0) + c.get("changed", 0) + c.get("lost", 0)
        return {
            "acquisitions": self.acquisitions,
            "audible_crosstalk_share": round(self.audible / n, 4),
            "ghost_share": round(self.ghost / n, 4),
            "marked_share": round(self.marked / n, 4),
            "ghost_unmarked_share": round(self.ghost_unmarked / n, 4),
            "restarts": self.restarts,
            "board_error_mm": _stats(self.board_errors),
            "board_tracked_error_mm": _stats(self.board_tracked_errors),
            "tracked_error_mm": _stats(self.tracked_errors),
            "tracked_error_in_view_mm": _stats(self.tracked_errors_in_view),
            "paired_error_mm": self.paired,
            "crossings": c,
            "crossings_kept_share": round(c.get("kept", 0) / tracked, 4) if tracked else None,
            "crossings_kept_share_of_all": round(c.get("kept", 0) / c["crossings"], 4)
            if c.get("crossings")
            else None,
            "mover_coverage": round(self.covered, 4),
            **({"oracle_association": self.oracle} if self.oracle else {}),
            "fused_records": self.cycles,
            "pipeline_ms_per_acquisition": round(1e3 * self.pipeline_s / n, 3),
            "fusion_ms_per_cycle": round(1e3 * self.fusion_s / max(self.cycles, 1), 3),
        }


def _stats(values) -> dict:
    if not values:
        return {"n": 0}
    a = np.asarray(values)
    return {
        "n": int(a.size),
        "mean": round(float(a.mean()), 2),
        "median": round(float(np.median(a)), 2),
    }


def run_virtual_robot(
    world,
    pipeline,
    *,
    cycles: int,
    scheduled: bool,
    seed: int = 0,
    ghosts: bool = True,
    drop_marked: bool = True,
    spec=None,
    coast: CoastPolicy | None | str = "robot",
    oracle: bool = False,
) -> tuple[RunFigures, list[dict]]:
    """``coast``: the fuser's coasting policy; "robot": the robot file's (robot/coast.py).
    ``oracle``: also score the same fused targets associated by the truth (``figs.oracle``)."""
    from tools.bench.robot_offline import simulate

    figs = RunFigures()
    acqs, figs.restarts, _ = simulate(
        world, cycles=cycles, scheduled=scheduled, seed=seed, want_clean=ghosts
    )
    sched = Schedule.from_robot(world.robot, window_s=world.n_samples / world.sample_rate_hz)
    marker = CrosstalkMarker(sched, world.names)
    fov = {b.name: b.field_of_view_deg for b in world.robot.boards}
    fuser = Fuser(
        world.mounts,
        period_s=sched.period_s,
        spec=spec,
        drop_marked=drop_marked,
        field_of_view_deg=fov,
        coast=CoastPolicy.from_robot(world.robot) if coast == "robot" else coast,
    )
    fire = {}
    records = []
    own = load_profile(world.robot.boards[0].profile).track  # what `run` tracks one board with
    own_trackers = {n: Tracker(own) for n in world.names}
    same_trackers = {n: Tracker(fuser.tracker.spec if fuser.tracker else own) for n in world.names}
    own_err: dict = {}  # (board, acquisition): {mover: error} of its own tracker, `run`'s [track]
    same_err: dict = {}  # ... with the fused tracker's [track]
    reported: dict = {}  # (board, acquisition): the movers it reported a target near
    for a in acqs:
        t = time.perf_counter()
        res = pipeline.process(
            a.frame.samples.astype(np.float64), a.frame.background.astype(np.float64)
        )
        figs.pipeline_s += time.perf_counter() - t
        figs.acquisitions += 1
        targets = reports_targets(res)
        audible = a.frame.foreign_peak >= 60.0
        figs.audible += audible
        ghost = False
        if ghosts and a.frame.clean is not None:
            clean = pipeline.process(
                a.frame.clean.astype(np.float64), a.frame.background.astype(np.float64)
            )
            ghost = _has_ghost(world, a, targets, reports_targets(clean))
        figs.ghost += ghost
        mapped = a.host_pulse  # the board's clock mapped as run --robot does (robot_offline)
        heard = marker.observe(a.board, mapped)
        figs.marked += bool(heard)
        figs.ghost_unmarked += ghost and not heard
        fire[(a.board, a.index)] = a.t_fire
        truth = world.movers_base(a.t_fire)
        own = [world.mounts[a.board].to_base(p) for p, _, _ in targets]
        m = score.match(np.array(own).reshape(-1, 3), truth)
        figs.board_errors += [d for _, d in m.values()]
        reported[(a.board, a.index)] = set(m)
        in_view = np.flatnonzero(world.in_view(a.board, truth))
        for trackers, errs in ((own_trackers, own_err), (same_trackers, same_err)):
            tracks = trackers[a.board].update(
                [BaseTarget(p, c, [a.board]) for p, c, _ in targets], a.board_us / 1e6
            )
            pos = np.array([world.mounts[a.board].to_base(t.position_mm) for t in tracks])
            m = score.match(pos.reshape(-1, 3), truth[in_view])
            errs[(a.board, a.index)] = {int(in_view[j]): d for j, (_, d) in m.items()}
        figs.board_tracked_errors += list(own_err[(a.board, a.index)].values())
        t = time.perf_counter()
        out = fuser.add(
            BoardReport(
                a.board,
                mapped,
                targets,
                acquisition=a.index,
                device_time_us=a.board_us,
                crosstalk=heard,
            )
        )
        records += out
        figs.fusion_s += time.perf_counter() - t
    records += fuser.flush()
    figs.cycles = len(records)
    truths = []
    for rec in records:
        ts = [fire[(name, b["acquisition"])] for name, b in rec["boards"].items()]
        truths.append(world.movers_base(float(np.mean(ts))))
    figs.truths = truths
    ids, figs.tracked_errors = score.coverage(records, truths)
    seen = [t[np.any([world.in_view(n, t) for n in world.names], axis=0)] for t in truths]
    _, figs.tracked_errors_in_view = score.coverage(records, seen)
    figs.covered = (
        float(np.mean([len(i) / max(len(t), 1) for i, t in zip(ids, truths, strict=True)]))
        if ids
        else 0.0
    )
    primary = score.primary_boards(world, truths)
    seen = [
        set().union(*(reported.get((n, b["acquisition"]), set()) for n, b in rec["boards"].items()))
        for rec in records
    ]
    figs.crossings = score.crossing_ids(ids, score.crossings(primary), seen, truths)
    if oracle:
        figs.oracle = _oracle_figures(world, fuser, coast, records, truths, primary)
    figs.paired = {
        "own": score.paired_errors(records, truths, primary, world.names, own_err),
        "same_track_settings": score.paired_errors(records, truths, primary, world.names, same_err),
    }
    return figs, records


def _oracle_figures(world, fuser, coast, records, truths, primary) -> dict:
    """Crossings and coverage of score.oracle_records: the fused tracker's settings and
    coasting, the truth's association."""
    spec = fuser.tracker.spec if fuser.tracker is not None else None

    def fresh_coast() -> CoastPolicy | None:  # one per tracker: a policy keeps per-track state
        if coast == "robot":
            return CoastPolicy.from_robot(world.robot)
        return copy.deepcopy(coast)

    oracle = score.oracle_records(records, truths, lambda: Tracker(spec), fresh_coast)
    ids, _ = score.coverage(oracle, truths)
    c = score.crossing_ids(ids, score.crossings(primary))
    tracked = c["kept"] + c["changed"] + c["lost"]
    return {
        "crossings": c,
        "crossings_kept_share": round(c["kept"] / tracked, 4) if tracked else None,
        "mover_coverage": round(
            float(np.mean([len(i) / max(len(t), 1) for i, t in zip(ids, truths, strict=True)])),
            4,
        ),
    }


def _has_ghost(world, acq, targets, clean_targets) -> bool:
    mount = world.mounts[acq.board]
    objects = np.vstack(
        [
            mount.to_board(world.movers_base(acq.t_fire)),
            mount.to_board(world.posts_base(acq.t_fire)),
        ]
    )
    clean = np.array([p for p, _, _ in clean_targets]).reshape(-1, 3)
    for p, _, _ in targets:
        if len(clean) and np.min(np.linalg.norm(clean - p, axis=1)) <= GHOST_NEW_MM:
            continue
        if np.min(np.linalg.norm(objects - p, axis=1)) <= GHOST_TRUTH_MM:
            continue
        return True
    return False
