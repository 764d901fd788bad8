"""``sim://[NAME][?key=value&...]``: the virtual board's options, parsed and validated.

The NAME tells boards apart within one process (two URLs with different names are two
boards); the query selects the scene and injects faults. Unknown keys are rejected.

Here in ``link`` (what a port URL means), below ``runtime`` and ``sim``: the live loop asks
whether a URL is a virtual board with a modelled envelope without importing the board.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from urllib.parse import parse_qsl, urlsplit

from spiel_edge.errors import ConfigError
from spiel_edge.link.usb_ids import BOARD_USB_IDS

SCENES = ("replay", "model", "robot")
# the hostile firmware modes of lie= (each acted out by sim/lies.py)
LIES = (
    "channels",
    "fewer-channels",
    "samples",
    "format",
    "channel-index",
    "counter-restart",
    "index-repeat",
    "incomplete",
    "mute-stream",
    "endless-config",
    "oversized-config",
    "mute-config",
    "start-channels",
    "hello-control",
    "start-at-ignored",
)


@dataclass(frozen=True)
class SimOptions:
    name: str = ""
    scene: str = "replay"  # replay: vendored real recordings; model: physical echo model
    seed: int = 0
    # faults, per direction of the byte stream (both ways) and per frame sent by the board
    ber: float = 0.0  # probability that a byte gets one bit flipped
    drop: float = 0.0  # probability that the board loses a frame it sends
    dup: float = 0.0  # probability that the board sends a frame twice
    unplug_after: int = 0  # vanish after this many acquisitions (0: never), then every as many
    unplug_ms: float = 500.0  # how long it stays away
    unplug_count: int = 0  # how many times (0: unlimited)
    stall_after: int = 0  # go silent (no data, no answers) after this many acquisitions
    stall_ms: float = 0.0
    power_cut: int = -1  # lose power at this flash operation (0-based), once
    fw_power_cut: int = -1  # lose power at this firmware-flash operation (0-based), once
    # protocol version 2 (docs/virtual-board.md)
    drift_ppm: float = 0.0  # the board's clock runs this much fast (+) or slow (-)
    jitter_us: float = 0.0  # each direction of a request/answer is delayed uniform [0, jitter]
    sync_fault: str = ""  # "months" / "backwards": every 7th TIME_SYNC answer is that wrong
    heartbeat_flags: int = 0  # extra HEARTBEAT error_flags bits (unknown ones: 0x8000)
    log_flood: float = 0.0  # LOG lines per second past the board's own limit (a bad firmware)
    watchdog_ms: float = 3000.0  # a trial image that never answers is reset after this
    trial_window_ms: float = 60000.0  # an unconfirmed trial stops kicking its watchdog after this
    no_sensor: bool = False  # the front end never answers: a trial's self-test fails
    start_at: bool = True  # offers START_AT (False: a version-2 firmware from before it)
    # identity
    serial: str = "SIM0001"
    vid: int = BOARD_USB_IDS[0][0]  # the board's own ids (link/usb_ids.py)
    pid: int = BOARD_USB_IDS[0][1]
    protocol: int = 2  # the highest protocol version the board speaks (1: a version-1 board)
    max_payload: int = 8256  # HELLO max_payload: the largest payload it sends or accepts
    fifo: int = 65536  # transmit buffer (bytes); a due acquisition that does not fit overruns
    # scene
    profile: str = "spiel-icra23"  # geometry and timing of the model scene
    targets: str = ""  # model: fixed targets "x,y,z;x,y,z" in mm (default: one orbiting)
    orbit: str = "60,150,8"  # model: radius mm, height mm, period s of the default target
    movers: int = 0  # model: this many targets on smooth random paths (sim/movers.py), 0..8
    noise: float = 20.0  # model: Gaussian noise (counts, std)
    speed: float = 0.0  # model: speed of sound in m/s (0: the profile's)
    shuffle: bool = False  # replay: random order instead of the recorded one
    lie: str = ""  # a hostile firmware mode (sim/lies.py): the board contradicts itself
    robot: str = ""  # robot: the robot file (or built-in name) whose shared scene this board sees
    board: str = ""  # robot: which of its boards this is (sim/robot.py)

    @classmethod
    def from_url(cls, url: str) -> SimOptions:
        parts = urlsplit(url)
        if parts.scheme.lower() != "sim":
            raise ConfigError(f"{url!r}: not a sim:// URL")
        values: dict[str, object] = {"name": (parts.netloc + parts.path).strip("/")}
        fields = {f.name: f for f in dataclasses.fields(cls)}
        for key, raw in parse_qsl(parts.query, keep_blank_values=True):
            if key not in fields or key == "name":
                allowed = ", ".join(sorted(k for k in fields if k != "name"))
                raise ConfigError(f"{url!r}: unknown option {key!r}; known: {allowed}")
            values[key] = _convert(url, key, raw, type(getattr(cls(), key)))
        options = cls(**values)  # type: ignore[arg-type]
        options.validate(url)
        return options

    def validate(self, origin: str = "sim") -> None:
        def need(ok: bool, msg: str) -> None:
            if not ok:
                raise ConfigError(f"{origin!r}: {msg}")

        need(self.scene in SCENES, f"scene must be one of {SCENES}, got {self.scene!r}")
        for key in ("ber", "drop", "dup"):
            value = getattr(self, key)
            need(0.0 <= value <= 1.0, f"{key} must be a probability in [0, 1], got {value}")
        need(
            min(self.unplug_after, self.unplug_count, self.stall_after) >= 0, "counts must be >= 0"
        )
        need(self.unplug_ms >= 0 and self.stall_ms >= 0, "durations must be >= 0")
        need(self.protocol in (1, 2), f"protocol must be 1 or 2, got {self.protocol}")
        need(
            64 <= self.max_payload <= 8256,
            f"max_payload must be in [64, 8256], got {self.max_payload}",
        )
        need(self.fifo >= 1024, f"fifo must be >= 1024 bytes, got {self.fifo}")
        need(
            self.noise >= 0 and (self.speed == 0 or 200 <= self.speed <= 2000),
            "noise >= 0, speed in [200, 2000]",
        )
        need(0 <= self.movers <= 8, f"movers must be in [0, 8], got {self.movers}")
        need(self.lie in ("", *LIES), f"lie must be one of {', '.join(LIES)}, got {self.lie!r}")
        need(0 < len(self.serial.encode()) <= 16, "serial must be 1 to 16 bytes")
        need(
            abs(self.drift_ppm) <= 30_000,
            f"drift_ppm must be in [-30000, 30000] (RC oscillators: 1-2 %), got {self.drift_ppm}",
        )
        need(0 <= self.jitter_us <= 1e6, f"jitter_us must be in [0, 1e6], got {self.jitter_us}")
        need(
            self.sync_fault in ("", "months", "backwards"),
            f"sync_fault must be months or backwards, got {self.sync_fault!r}",
        )
        need(0 <= self.heartbeat_flags <= 0xFFFFFFFF, "heartbeat_flags must be a u32")
        need(0 <= self.log_flood <= 100000, f"log_flood must be in [0, 1e5], got {self.log_flood}")
        need(self.watchdog_ms > 0, "watchdog_ms must be > 0")
        need(self.trial_window_ms > 0, "trial_window_ms must be > 0")
        need(0 <= self.vid <= 0xFFFF and 0 <= self.pid <= 0xFFFF, "vid and pid must be 16-bit")


def modelled_envelope(url: str) -> bool:
    """Whether ``url`` is a virtual board measuring the physical echo model (``scene=model``).

    Its envelope is an idealised pulse, not the CH101's: the learned ToA correction, fitted
    to the prototype's recordings, moves its exact arrival times (mean error of the default
    orbiting target 5.1 mm without it, 10.1 mm with it; docs/virtual-board.md), so the
    pipelines built for such a board leave it out unless asked for."""
    if not url.lower().startswith("sim:"):
        return False
    try:
        return SimOptions.from_url(url).scene in ("model", "robot")
    except ConfigError:
        return False


def _convert(url: str, key: str, raw: str, kind: type) -> object:
    try:
        if kind is bool:
            if raw.lower() not in ("1", "0", "true", "false", "yes", "no", ""):
                raise ValueError(raw)
            return raw.lower() in ("1", "true", "yes", "")
        if kind is int:
            return int(raw, 0)
        if kind is float:
            value = float(raw)
            if not math.isfinite(value):
                raise ValueError(raw)
            return value
        return raw
    except ValueError:
        raise ConfigError(f"{url!r}: option {key} must be {kind.__name__}, got {raw!r}") from None
