"""Time division of the boards' pulses: trigger slots, the guard time, and marking.

Board A listens for ``W`` seconds after its pulse (its window: n_samples / sample rate). A
pulse of board B at ``t_B`` is heard by A while its echoes last, up to the farthest audible
echo ``2 R / c`` (R = ``[trigger] max_range_m``, the guard time), so A's window is clean when
``t_B`` lies outside ``[t_A - 2R/c, t_A + W]``. Slots of length
``max(W, 2 R / c) + 2 u`` (u: the clock-sync uncertainty, ``sync_margin_ms``) that do not
overlap modulo the period keep every pair apart in both directions. An acquisition whose
window was reached by another board's pulse all the same (a board out of its slot: a reset,
drift, a board that ignores the schedule) is *marked*.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from spiel_edge.errors import ConfigError

EMISSIONS_KEPT = 8  # per board: recent pulses remembered for marking


@dataclass(frozen=True)
class Slot:
    board: str
    offset_s: float  # start within the period


class Schedule:
    """The slots of a robot's boards within one period, checked to be disjoint."""

    def __init__(
        self,
        slots: list[Slot],
        *,
        period_s: float,
        window_s: float,
        guard_s: float,
        margin_s: float,
        origin: str = "robot",
    ):
        self.period_s = period_s
        self.window_s = window_s
        self.guard_s = guard_s
        self.margin_s = margin_s
        self.slot_s = max(window_s, guard_s) + 2.0 * margin_s
        self.slots = {s.board: s for s in slots}
        self._check(slots, origin)

    @classmethod
    def from_robot(cls, robot, window_s: float | None = None) -> Schedule:
        t = robot.trigger
        if window_s is None:
            window_s = t.window_ms / 1000.0 if t.window_ms > 0 else _profile_window(robot)
        guard_s = 2.0 * t.max_range_m / t.speed_of_sound_m_s
        margin_s = t.sync_margin_ms / 1000.0
        slot_s = max(window_s, guard_s) + 2.0 * margin_s
        slots = [
            Slot(b.name, b.slot_ms / 1000.0 if b.slot_ms is not None else b.slot * slot_s)
            for b in robot.boards
        ]
        return cls(
            slots,
            period_s=t.period_ms / 1000.0,
            window_s=window_s,
            guard_s=guard_s,
            margin_s=margin_s,
            origin=robot.origin,
        )

    def _check(self, slots: list[Slot], origin: str) -> None:
        s, p = self.slot_s, self.period_s
        need = len(slots) * s
        if need > p + 1e-12:
            raise ConfigError(
                f"{origin}: trigger.period_ms {p * 1e3:g} is too short for {len(slots)} boards: "
                f"each slot needs {s * 1e3:.2f} ms (window {self.window_s * 1e3:.2f} ms, guard "
                f"{self.guard_s * 1e3:.2f} ms for max_range_m, 2 x sync margin); at least "
                f"{need * 1e3:.2f} ms"
            )
        for a in slots:
            if not 0.0 <= a.offset_s < p:
                raise ConfigError(
                    f"{origin}: board {a.board!r}: its slot starts at {a.offset_s * 1e3:g} ms, "
                    f"outside the {p * 1e3:g} ms period"
                )
        for i, a in enumerate(slots):
            for b in slots[i + 1 :]:
                gap = (b.offset_s - a.offset_s) % p
                if gap < s - 1e-9 or p - gap < s - 1e-9:
                    raise ConfigError(
                        f"{origin}: the trigger slots of boards {a.board!r} "
                        f"({a.offset_s * 1e3:.2f} ms) and {b.board!r} ({b.offset_s * 1e3:.2f} ms) "
                        f"overlap: slots start at least {s * 1e3:.2f} ms apart (modulo the "
                        f"{p * 1e3:g} ms period)"
                    )

    @property
    def span_s(self) -> float:
        """From the first slot's start to the last slot's end."""
        offsets = [s.offset_s for s in self.slots.values()]
        return max(offsets) - min(offsets) + self.slot_s

    def fire_time(self, board: str, t0: float, cycle: int) -> float:
        """Host time of ``board``'s pulse in ``cycle`` of a schedule started at ``t0``."""
        return t0 + cycle * self.period_s + self.slots[board].offset_s

    def next_fire(self, board: str, t0: float, after: float) -> float:
        """The first pulse time of ``board`` at or after ``after``."""
        base = t0 + self.slots[board].offset_s
        k = max(0, -int(-(after - base) // self.period_s))
        return base + k * self.period_s

    def phase_error(self, board: str, t0: float, t_fire: float) -> float:
        """Signed seconds from ``board``'s nearest slot start to ``t_fire``."""
        base = t0 + self.slots[board].offset_s
        x = (t_fire - base) % self.period_s
        return x - self.period_s if x > self.period_s / 2 else x

    def hears(self, t_listen: float, t_pulse: float, margin_s: float | None = None) -> bool:
        """Whether a pulse at ``t_pulse`` reaches a window opened at ``t_listen``."""
        u = self.margin_s if margin_s is None else margin_s
        return t_listen - self.guard_s - u <= t_pulse <= t_listen + self.window_s + u


class CrosstalkMarker:
    """Marks acquisitions whose window another board's pulse reached, from the pulses' host
    times (the boards' stamps mapped through their clocks): past pulses as seen, and each
    other board's next pulse predicted one period after its last.

    A pair's window is widened by what is unknown of its two times. A pulse TIME_SYNC measured
    brings its stated uncertainty (tens of microseconds); a pulse from the one-way estimate, or
    reported at its slot's time, may be anywhere its slot keeping allows, up to the margin
    either way. Two such pulses widen by one margin together (each is kept within the margin of
    its slot, so the slots' two margins still part them); one of them beside a measured pulse
    widens by the margin plus the measured uncertainty; two measured pulses by the sum of
    theirs, so boards that TIME_SYNC shows well inside their slots are not marked."""

    def __init__(self, schedule: Schedule, boards: list[str]):
        self.schedule = schedule
        self._pulses: dict[str, deque[tuple[float, float | None]]] = {
            b: deque(maxlen=EMISSIONS_KEPT) for b in boards
        }
        self.marked: dict[str, int] = dict.fromkeys(boards, 0)
        self.seen: dict[str, int] = dict.fromkeys(boards, 0)

    def observe(
        self,
        board: str,
        t_host: float,
        period_s: float | None = None,
        uncertainty_s: float | None = None,
    ) -> list[str]:
        """Record ``board``'s pulse at ``t_host`` (± ``uncertainty_s`` when measured: finite
        and not negative, else unknown); the boards whose pulse reached its window."""
        period = self.schedule.period_s if period_s is None else period_s
        mine = uncertainty_s
        if mine is not None and not (math.isfinite(mine) and mine >= 0):
            mine = None
        heard = []
        for other, pulses in self._pulses.items():
            if other == board or not pulses:
                continue
            last_t, last_u = pulses[-1]
            candidates = list(pulses) + [(last_t + period, last_u)]
            if any(self.schedule.hears(t_host, t, self._widening(mine, u)) for t, u in candidates):
                heard.append(other)
        self._pulses[board].append((t_host, mine))
        self.seen[board] += 1
        if heard:
            self.marked[board] += 1
        return heard

    def _widening(self, a: float | None, b: float | None) -> float:
        margin = self.schedule.margin_s
        if a is None and b is None:
            return margin
        return (margin if a is None else a) + (margin if b is None else b)


def _profile_window(robot) -> float:
    from spiel_edge.profile.schema import resolve_profile

    window = 0.0
    for b in robot.boards:
        try:
            p = resolve_profile(b.profile, b.calibration)
        except ConfigError as exc:
            raise ConfigError(f"{robot.origin}: board {b.name!r}: {exc}") from exc
        window = max(window, p.acquisition.n_samples / p.acquisition.sample_rate_hz)
    return window
