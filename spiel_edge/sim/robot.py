"""The virtual robot: N boards on one robot moving through a room, hearing each other.

One :class:`RobotWorld` holds the robot (its boards' mounts from a robot description,
robot/description.py), its path through a room of static reflectors (posts) in ``odom``,
and movers walking around it. Each board hears

- its own pulse's echoes off every post and mover (the board's echo model of sim/scenes.py,
  weighted by a beam pattern: ``exp(-(theta / BEAM_WIDTH)^2)`` off the board's facing on the
  way out and back, nothing behind the board, and air absorption);
- every *other* board's pulse: the direct path from that emitter to its receivers (coupling
  through the robot's body and the air, ``direct_gain / d``) and that pulse's echoes
  (emitter j -> object -> receiver of i), shifted by the time between the two pulses.

So several boards around one scene show the cross-talk problem, and a schedule
(robot/schedule.py) shows its cure. Truth is in ``base_link`` (the robot's frame) and per
board in its own frame.

Reached as ``sim://NAME?scene=robot&robot=FILE&board=NAME&movers=N&seed=S`` (one shared world
per robot file, movers and seed in a process, so several boards' URLs see one scene), or
offline through tools/bench/robot_offline.py's ``simulate`` (tools/bench/robot_eval.py, tests/robot/):
pulses in virtual time, each board with its own clock (offset and drift) and a link latency.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from spiel_edge.profile.schema import load_profile
from spiel_edge.robot.description import RobotSpec
from spiel_edge.sim.scenes import (
    U16_MAX,
    EchoModel,
    EchoModelScene,
    SceneFrame,
    emg_mode,
    erf_array,
)

BEAM_WIDTH_DEG = 80.0  # e-folding half-angle of the transducer's beam (each way)
ABSORPTION_PER_M = 0.6  # air at 175 kHz: about 5 dB per metre of path
MOVER_REFLECTIVITY = 3.0e7  # a person's leg or a box: stronger than the lab's target
POST_REFLECTIVITY = 2.0e7
DIRECT_GAIN = 2.0e4  # another board's pulse heard directly: amplitude x distance (counts mm)
AUDIBLE_COUNTS = 60.0  # a foreign arrival at least this strong in the window contaminates it


@dataclass(frozen=True)
class Room:
    """Static reflectors (posts) in odom, mm; the robot drives a circle among them."""

    posts_mm: np.ndarray = field(
        default_factory=lambda: np.array(
            [
                [480.0 * math.cos(a), 480.0 * math.sin(a), 0.0]
                for a in np.radians([20, 95, 160, 215, 290, 340])
            ]
        )
    )
    path_radius_mm: float = 150.0  # the robot's centre drives this circle ...
    path_period_s: float = 60.0  # ... once in this long, facing along it


class Movers:
    """Targets walking around the robot: azimuth, radius (from the robot's centre) and height
    each a smooth seeded function of time; they follow the robot (they are curious) and pass
    from one board's field of view into the next."""

    def __init__(self, n: int, *, seed: int = 0, height_mm: float = 0.0):
        rng = np.random.default_rng([seed, 0x20B07])
        self.n = n
        self.phi0 = rng.uniform(0, 2 * np.pi, n)
        self.omega = rng.uniform(0.25, 0.8, n) * rng.choice([-1.0, 1.0], n)  # rad/s
        self.r0 = rng.uniform(230.0, 330.0, n)
        self.r_amp = rng.uniform(10.0, 50.0, n)
        self.r_rate = rng.uniform(0.2, 0.6, n)
        self.z_amp = rng.uniform(10.0, 40.0, n)
        self.z_rate = rng.uniform(0.2, 0.5, n)
        self.phase = rng.uniform(0, 2 * np.pi, (n, 2))
        self.height_mm = height_mm

    def relative(self, t: float) -> np.ndarray:
        """(n, 3) mm from the robot's centre, in odom's axes."""
        phi = self.phi0 + self.omega * t
        r = self.r0 + self.r_amp * np.sin(self.r_rate * t + self.phase[:, 0])
        z = self.height_mm + self.z_amp * np.sin(self.z_rate * t + self.phase[:, 1])
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


@dataclass
class BoardFrame:
    samples: np.ndarray  # (channels, n) uint16
    background: np.ndarray  # (channels, n) uint16: the board's own static scene
    truth_board_mm: np.ndarray  # (K, 3) movers in the board's frame
    foreign_peak: float  # strongest foreign arrival inside the window (after the blind zone)
    clean: np.ndarray | None = None  # the same frame without foreign pulses (when they mattered)


class RobotWorld:
    """See the module docstring."""

    def __init__(
        self,
        robot: RobotSpec,
        *,
        movers: int = 5,
        seed: int = 0,
        room: Room | None = None,
        noise: float = 20.0,
        profile: str | None = None,
        moving: bool = True,
    ):
        self.robot = robot
        self.names = [b.name for b in robot.boards]
        self.room = room or Room()
        self.moving = moving
        self.movers = Movers(movers, seed=seed)
        self.noise = noise
        prof = load_profile(profile or robot.boards[0].profile)
        self.geometry = g = prof.geometry
        self.sample_rate_hz = prof.acquisition.sample_rate_hz
        self.n_samples = prof.acquisition.n_samples
        self.mm_per_sample = g.speed_of_sound_m_s * 1000.0 / self.sample_rate_hz
        self.blind = prof.preprocess.blind_zone_samples
        self.delays = g.delays()
        self.listening = g.listening_mask()
        self._model = EchoModel()
        self._scene = EchoModelScene(
            g, sample_rate_hz=self.sample_rate_hz, n_samples=self.n_samples
        )
        self.mounts = {b.name: b.mount for b in robot.boards}
        self.emitters = {n: m.to_base(g.emitter_mm) for n, m in self.mounts.items()}
        self.receivers = {n: m.to_base(g.channels_mm) for n, m in self.mounts.items()}
        self.facing = {n: m.facing for n, m in self.mounts.items()}
        # the EMG pulse shape on a fine grid: interpolated instead of erf per sample
        mode = emg_mode(self._model.sigma, self._model.eta)
        self._grid = np.linspace(-12.0, 24.0, 3601)
        u = (self._grid + mode) / self._model.sigma
        raw = np.exp(-0.5 * u * u) * (1.0 + erf_array(self._model.eta * u / math.sqrt(2.0)))
        self._shape = raw / raw.max()
        self._rng = np.random.default_rng([seed, 0x5EED])
        self._lock = threading.Lock()
        self._pulses: dict[str, deque[float]] = {n: deque(maxlen=4) for n in self.names}

    # --- where things are --------------------------------------------------------------

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of base_link in odom: the robot drives its circle, facing along it."""
        room = self.room
        a = 2 * math.pi * t / room.path_period_s if self.moving else 0.0
        x, y = room.path_radius_mm * math.cos(a), room.path_radius_mm * math.sin(a)
        yaw = a + math.pi / 2
        c, s = math.cos(yaw), math.sin(yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.array([x, y, 0.0])

    def movers_base(self, t: float) -> np.ndarray:
        """(n, 3) movers in base_link, mm."""
        rot, _ = self.pose(t)
        return self.movers.relative(t) @ rot  # R^T v for each row

    def posts_base(self, t: float) -> np.ndarray:
        rot, trans = self.pose(t)
        return (self.room.posts_mm - trans) @ rot

    def in_view(self, board: str, p_base: np.ndarray, half_angle_deg: float = 50.0) -> np.ndarray:
        v = np.atleast_2d(p_base) - self.emitters[board]
        cos = v @ self.facing[board] / np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        return cos >= math.cos(math.radians(half_angle_deg))

    def _beam(self, board: str, p: np.ndarray) -> np.ndarray:
        v = p - self.emitters[board]
        d = np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        cos = np.clip(v @ self.facing[board] / d, -1.0, 1.0)
        theta = np.degrees(np.arccos(cos))
        return np.where(cos > 0, np.exp(-((theta / BEAM_WIDTH_DEG) ** 2)), 0.0)

    # --- what a board hears ------------------------------------------------------------

    def frame(
        self,
        board: str,
        t_fire: float,
        pulses: list[tuple[str, float]],
        *,
        crosstalk: bool = True,
        want_clean: bool = False,
    ) -> BoardFrame:
        """Board ``board``'s acquisition with its pulse at ``t_fire`` (seconds, true time),
        hearing the other boards' ``pulses`` ((board, time) pairs)."""
        n = self.n_samples
        background = self._scene.background(n)
        objects = np.vstack([self.movers_base(t_fire), self.posts_base(t_fire)])
        refl = np.concatenate(
            [
                np.full(self.movers.n, MOVER_REFLECTIVITY),
                np.full(len(self.room.posts_mm), POST_REFLECTIVITY),
            ]
        )
        own = self._render(*self._echoes(board, board, objects, refl, 0.0))
        parts = []
        if crosstalk:
            for other, t_other in pulses:
                if other == board:
                    continue
                shift = (t_other - t_fire) * self.sample_rate_hz
                if shift > n + 4 or shift < -2 * n:
                    continue
                parts.append(self._echoes(other, board, objects, refl, shift))
                parts.append(self._direct(other, board, shift))
        if parts:
            foreign = self._render(
                np.vstack([p[0] for p in parts]), np.vstack([p[1] for p in parts])
            )
        else:
            foreign = np.zeros_like(own)
        noise = self._rng.normal(0.0, self.noise, own.shape) if self.noise else 0.0
        base = background + own + noise
        samples = _u16(base + foreign)
        peak = float(foreign[:, self.blind :].max()) if foreign.size else 0.0
        clean = _u16(base) if want_clean and peak >= AUDIBLE_COUNTS else None
        truth = self.mounts[board].to_board(self.movers_base(t_fire))
        return BoardFrame(samples, background, truth, peak, clean)

    def _echoes(self, emitter_board, board, objects, refl, shift):
        """Arrival (samples) and amplitude (counts) per object and channel: (K, C) each."""
        e = self.emitters[emitter_board]
        rx = self.receivers[board]
        d_tx = np.maximum(np.linalg.norm(objects - e, axis=1), 1.0)[:, None]
        gain = (refl * self._beam(emitter_board, objects) * self._beam(board, objects))[:, None]
        d_rx = np.maximum(np.linalg.norm(objects[:, None, :] - rx[None], axis=2), 1.0)
        path = d_tx + d_rx
        amp = gain * np.exp(-ABSORPTION_PER_M * path / 1000.0) / (d_tx * d_rx)
        return path / self.mm_per_sample + self.delays + shift, amp

    def _direct(self, emitter_board, board, shift):
        d = np.maximum(
            np.linalg.norm(self.receivers[board] - self.emitters[emitter_board], axis=1), 1.0
        )
        return (d / self.mm_per_sample + 2.0 + shift)[None], (DIRECT_GAIN / d)[None]

    def _render(self, toa: np.ndarray, amp: np.ndarray) -> np.ndarray:
        """The sum of EMG pulses at ``toa`` of height ``amp`` ((M, C) each) -> (C, n)."""
        n = self.n_samples
        keep = (amp >= 1.0) & self.listening[None, :] & (toa > -24) & (toa < n + 12)
        amp = np.where(keep, amp, 0.0)
        t = np.arange(n, dtype=np.float64)
        x = t[None, None, :] - toa[:, :, None]
        shape = np.interp(x.ravel(), self._grid, self._shape, left=0.0, right=0.0)
        return (shape.reshape(x.shape) * amp[:, :, None]).sum(axis=0)

    # --- live: one board of the world behind sim:// ------------------------------------

    def live_frame(self, board: str, t_fire: float) -> BoardFrame:
        """For :class:`RobotBoardScene`: the other boards' pulses as they happened (and each
        one's next, one interval after its last), on the host's clock."""
        with self._lock:
            pulses = []
            for other, seen in self._pulses.items():
                if other == board or not seen:
                    continue
                pulses += [(other, t) for t in seen]
                if len(seen) >= 2:
                    pulses.append((other, seen[-1] + (seen[-1] - seen[-2])))
            self._pulses[board].append(t_fire)
            return self.frame(board, t_fire, pulses)


def _u16(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, U16_MAX).astype(np.uint16)


class RobotBoardScene:
    """One board of a shared :class:`RobotWorld`, as a virtual board's scene."""

    def __init__(self, world: RobotWorld, board: str):
        if board not in world.names:
            from spiel_edge.errors import ConfigError

            raise ConfigError(
                f"sim: scene=robot: no board {board!r} in the robot ({', '.join(world.names)})"
            )
        self.world, self.board = world, board
        self.geometry = world.geometry
        self.n_channels = len(world.delays)
        self.n_samples = world.n_samples
        self.sample_rate_hz = int(round(world.sample_rate_hz))
        self.speed = world.geometry.speed_of_sound_m_s
        self._boot = 0.0

    def on_boot(self, now: float) -> None:
        """The virtual board (re)booted at host time ``now``: its stamps count from there."""
        self._boot = now

    def supports(self, n_samples: int) -> bool:
        return n_samples == self.n_samples

    def frame(self, index: int, n_samples: int, time_s: float) -> SceneFrame:
        del index, n_samples
        f = self.world.live_frame(self.board, self._boot + time_s)
        truth = f.truth_board_mm
        return SceneFrame(f.samples, f.background, truth[0].copy() if len(truth) else None, truth)


_WORLDS: dict[tuple, RobotWorld] = {}
_WORLDS_LOCK = threading.Lock()


def board_scene(options) -> RobotBoardScene:
    """The scene of ``sim://...?scene=robot&robot=FILE&board=NAME`` (one world per robot file,
    movers and seed in this process)."""
    from spiel_edge.errors import ConfigError
    from spiel_edge.robot.description import load_robot

    if not options.robot or not options.board:
        raise ConfigError("sim: scene=robot needs robot=FILE and board=NAME")
    key = (options.robot, options.movers, options.seed, options.noise)
    with _WORLDS_LOCK:
        world = _WORLDS.get(key)
        if world is None:
            world = _WORLDS[key] = RobotWorld(
                load_robot(options.robot),
                movers=options.movers,
                seed=options.seed,
                noise=options.noise,
            )
    return RobotBoardScene(world, options.board)
