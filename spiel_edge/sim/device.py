"""The virtual board on its cable: plug state, line faults and the transmit FIFO.

One SimDevice outlives its links, like a board outlives the file descriptors opened on it:
``unplug_after`` makes it vanish (reads and writes of the links opened on it fail, new opens
fail) and come back ``unplug_ms`` later rebooted, with the same serial number. Time comes
from the caller (``now``), so the in-process pyserial handler, the pty server and the fake
USB backend all drive the same object.
"""

from __future__ import annotations

import errno
import logging
import random
import time
from collections.abc import Callable

from spiel_edge.link.sim_options import SimOptions
from spiel_edge.sim.board import VirtualBoard
from spiel_edge.sim.faults import LineFaults
from spiel_edge.sim.firmware_slots import FirmwareFlash
from spiel_edge.sim.flash import Flash, PowerCut
from spiel_edge.sim.lies import install as install_lie
from spiel_edge.sim.scenes import build_scene

log = logging.getLogger(__name__)

REBOOT_S = 0.3  # how long a rebooting board is gone from the bus
UNPLUG_GRACE_S = 0.2  # how long an unplug waits for the host to read what was already sent
ANSWER_SPIN_S = 0.0004  # the last stretch before a delayed answer is spun, not slept (wait())


class DeviceGone(OSError):
    """The virtual board is unplugged, or the link was opened before it last went away."""

    def __init__(self, what: str = "device disconnected"):
        super().__init__(errno.ENODEV, what)


def _scene(options: SimOptions):
    if options.scene == "robot":  # one board of a virtual robot's shared scene (sim/robot.py)
        from spiel_edge.sim.robot import board_scene

        return board_scene(options)
    return build_scene(options)


class SimDevice:
    def __init__(self, options: SimOptions, *, clock: Callable[[], float] = time.monotonic):
        now = clock()
        self.options = options
        self.clock = clock
        self.board = VirtualBoard(
            _scene(options),
            serial=options.serial,
            vid=options.vid,
            pid=options.pid,
            flash=Flash(cut_at=options.power_cut),
            seed=options.seed,
            now=now,
            protocol=options.protocol,
            drift_ppm=options.drift_ppm,
            firmware=FirmwareFlash(cut_at=options.fw_power_cut),
            sync_fault=options.sync_fault,
            heartbeat_flags=options.heartbeat_flags,
            log_flood=options.log_flood,
            max_payload=options.max_payload,
        )
        self.board.offers_start_at = options.start_at
        install_lie(self.board, options.lie)  # a hostile firmware mode, when asked
        self.faults = LineFaults(options.ber, options.drop, options.dup, seed=options.seed + 1)
        self.generation = 1  # +1 each time it comes back
        self.plugged = True
        self.unplugs = 0
        self.power_cuts = 0
        self.plug_times: list[float] = []  # when it came back, on the caller's clock
        self.holder: object | None = None  # the link holding it open (exclusive access)
        self.drained: Callable[[], bool] = lambda: True  # pty server: has the host read it all?
        self._replug_at = 0.0
        self._tx = bytearray()
        self._since_plug = 0
        self._sent = 0
        self._vanish_since: float | None = None
        self._stalled_until: float | None = None
        self._stalled = False
        # a jittered link: answers wait here until their time (release time, bytes)
        self._delayed: list[tuple[float, bytes]] = []
        self._jitter_rng = random.Random(options.seed + 7)
        self._silent_since: float | None = None

    # --- the host's side -----------------------------------------------------------------

    def write(self, data: bytes, generation: int | None = None) -> None:
        now = self.clock()
        self.update(now)
        self._check(generation)
        if self._stalled_until is not None:
            return  # frozen firmware: the bytes are lost
        jitter = self.options.jitter_us / 1e6
        up = self._jitter_rng.uniform(0.0, jitter) if jitter else 0.0
        try:
            replies = self.board.receive(self.faults.incoming(bytes(data)), now + up)
        except PowerCut as exc:
            log.info("%s: %s", self.options.serial, exc)
            self.power_cuts += 1
            self.unplug(now, self.options.unplug_ms / 1000.0)
            return
        wire = self.faults.outgoing(replies)
        if jitter and wire:
            down = self._jitter_rng.uniform(0.0, jitter)
            release = max(now + up + down, self._delayed[-1][0] if self._delayed else 0.0)
            self._delayed.append((release, wire))
        else:
            self._tx += wire

    def peek(self, max_bytes: int, generation: int | None = None) -> bytes:
        self.update(self.clock())
        self._check(generation)
        return bytes(self._tx[:max_bytes])

    def pending(self, generation: int | None = None) -> int:
        self.update(self.clock())
        self._check(generation)
        return len(self._tx)

    def consume(self, n: int) -> None:
        del self._tx[:n]

    def read(self, max_bytes: int, generation: int | None = None) -> bytes:
        data = self.peek(max_bytes, generation)
        self.consume(len(data))
        return data

    def discard_output(self) -> None:
        self._tx.clear()

    def _check(self, generation: int | None) -> None:
        if not self.plugged or (generation is not None and generation != self.generation):
            raise DeviceGone()

    # --- time ----------------------------------------------------------------------------

    def update(self, now: float) -> None:
        """Advance the board to ``now``: replug, reboot, stall, vanish, stream."""
        if not self.plugged:
            if now < self._replug_at:
                return
            self._plug(now)
        board = self.board
        while self._delayed and self._delayed[0][0] <= now:
            self._tx += self._delayed.pop(0)[1]
        board.no_sensor = self.options.no_sensor
        board.trial_window_s = self.options.trial_window_ms / 1000.0
        if board.trial_expired(now):  # an unconfirmed trial stopped kicking its watchdog
            log.info("%s: watchdog reset of an unconfirmed trial image", self.options.serial)
            self.unplug(now, REBOOT_S)
            return
        if board.silent and board.fw.boot_state != 0:  # a trial image that hangs
            if self._silent_since is None:
                self._silent_since = now
            elif now - self._silent_since >= self.options.watchdog_ms / 1000.0:
                log.info("%s: watchdog reset of a silent trial image", self.options.serial)
                self._silent_since = None
                self.unplug(now, REBOOT_S)
                return
        else:
            self._silent_since = None
        if board.reboot_at is not None and now >= board.reboot_at:
            self.unplug(now, REBOOT_S)
            return
        if self._stalled_until is not None:
            if now < self._stalled_until:
                return
            self._stalled_until = None
            board.skip_to(now)
        if self._vanish_since is not None:
            if (not self._tx and self.drained()) or now - self._vanish_since > UNPLUG_GRACE_S:
                self.unplug(now, self.options.unplug_ms / 1000.0)
            return
        self._stream(now)

    def _stream(self, now: float) -> None:
        opts = self.options
        limits = []  # stop exactly at the acquisition that triggers a fault
        if opts.unplug_after and self._unplugs_left():
            limits.append(max(opts.unplug_after - self._since_plug, 0))
        if opts.stall_after and not self._stalled:
            limits.append(max(opts.stall_after - self._sent, 0))
        limit = min(limits) if limits else None
        frames = self.board.due(now, self.options.fifo - len(self._tx), limit)
        if frames:
            self._tx += self.faults.outgoing(frames)
            self.board.tx_dropped = self.faults.stats.dropped_frames
            sent = len({f.acquisition for f in frames if f.acquisition is not None})
            self._since_plug += sent
            self._sent += sent
        if opts.stall_after and not self._stalled and self._sent >= opts.stall_after:
            self._stalled = True
            self._stalled_until = now + opts.stall_ms / 1000.0
        elif opts.unplug_after and self._unplugs_left() and self._since_plug >= opts.unplug_after:
            self._vanish_since = now

    def _unplugs_left(self) -> bool:
        return not self.options.unplug_count or self.unplugs < self.options.unplug_count

    def unplug(self, now: float, duration_s: float) -> None:
        log.debug("%s: unplugged for %.3f s", self.options.serial, duration_s)
        self.plugged = False
        self.unplugs += 1
        self._replug_at = now + duration_s
        self._vanish_since = None
        self._tx.clear()
        self._delayed.clear()
        self.faults.reset()
        self.holder = None

    def _plug(self, now: float) -> None:
        self.plugged = True
        self.plug_times.append(self._replug_at)
        self.generation += 1
        self._since_plug = 0
        self.board.boot(now)
        log.debug("%s: plugged in again (generation %d)", self.options.serial, self.generation)

    def wait(self, now: float, deadline: float | None, min_sleep_s: float) -> None:
        """Sleep a reading link until something may happen (or ``deadline``).

        A jittered link's delayed answer is waited for to within a few us: sleep overshoots
        by 50-100 us (the kernel's timer slack, more under load), which would delay only
        the answer's leg of a TIME_SYNC exchange, an asymmetry the link model does not have
        and no two-way exchange can see. So the last ANSWER_SPIN_S before it is spun."""
        wake = self.next_event(now)
        if deadline is not None:
            wake = min(wake, deadline)
        answer = self._delayed[0][0] if self._delayed else None
        if answer is None or answer > wake:
            time.sleep(max(wake - now, min_sleep_s))
        elif answer - now > ANSWER_SPIN_S:
            time.sleep(answer - ANSWER_SPIN_S - now)
        else:
            while self.clock() < answer:
                pass

    def next_event(self, now: float) -> float:
        """When something may happen next without host input (for sleeping callers)."""
        if not self.plugged:
            return self._replug_at
        times = [now + 0.05]
        if self._delayed:
            times.append(self._delayed[0][0])
        for t in (self._stalled_until, self.board.reboot_at, self.board.next_due()):
            if t is not None:
                times.append(t)
        if self._vanish_since is not None:
            times.append(now + 0.005)
        return max(min(times), now)
