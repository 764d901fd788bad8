"""The robot description: one TOML file listing a robot's boards (``run --robot FILE``).

```toml
[robot]
name = "rover"
frame_id = "base_link"          # REP 105: the robot's body frame (x forward, y left, z up)

[trigger]                       # time division (robot/schedule.py)
period_ms = 40.0                # one cycle: every board fires once
max_range_m = 1.0               # farthest audible echo: sets the guard time 2 R / c
sync_margin_ms = 0.5            # clock-sync uncertainty allowed on either side of a slot

[[board]]
name = "front"
port = "/dev/ttyACM0"           # or usb://VID:PID/SERIAL, sim://..., or a Zenoh key for `fuse`
profile = "spiel-icra23"
calibration = ""                # optional calibration .toml over the profile
translation_m = [0.10, 0.0, 0.20]
rotation_rpy_deg = [0.0, 90.0, 0.0]   # or rotation_xyzw = [...], or rotation_matrix = [[...]x3]
slot = 0                        # trigger slot index (or slot_ms = start within the period)
auth_key_file = "keys/front.key"  # optional, `fuse`: records must carry this key's tag
```

The mount maps the board's frame (the profile's geometry: z along the board's facing) into
``base_link``: ``p_base = R p_board + t`` (metres for t, the rotation as tf2's ``setRPY``).
Every problem is one :class:`ConfigError` line naming the file and the key.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from spiel_edge.compat import tomllib
from spiel_edge.errors import ConfigError
from spiel_edge.outputs.zenoh import publish_key_problem
from spiel_edge.profile.frame_section import frame_id_problem, quaternion_from_rpy

MAX_BOARDS = 16
MAX_FILE_BYTES = 256 * 1024
ROTATION_TOLERANCE = 1e-3  # |R^T R - I| and |det R - 1| allowed (rounded digits)
DETECTION_DEG = 55.0  # a board's default detection half-angle (docs/robot.md: chosen on seeds 1, 4)
_BOARD_KEYS = {
    "name",
    "port",
    "key",
    "profile",
    "calibration",
    "translation_m",
    "rotation_rpy_deg",
    "rotation_xyzw",
    "rotation_matrix",
    "slot",
    "slot_ms",
    "field_of_view_deg",
    "detection_deg",
    "auth_key_file",
}


@dataclass(frozen=True)
class Mount:
    """A rigid transform board -> base_link: rotation (3, 3) and translation (3,) in mm."""

    rotation: np.ndarray
    translation_mm: np.ndarray

    def to_base(self, p_board_mm: np.ndarray) -> np.ndarray:
        return np.asarray(p_board_mm, float) @ self.rotation.T + self.translation_mm

    def to_board(self, p_base_mm: np.ndarray) -> np.ndarray:
        return (np.asarray(p_base_mm, float) - self.translation_mm) @ self.rotation

    def covariance_to_base(self, c_board: np.ndarray) -> np.ndarray:
        r = self.rotation
        return r @ np.asarray(c_board, float) @ r.T

    @property
    def facing(self) -> np.ndarray:
        """The board's boresight (its z axis) in base_link."""
        return self.rotation[:, 2].copy()


@dataclass(frozen=True)
class BoardSpec:
    name: str
    port: str
    profile: str
    calibration: str | None
    mount: Mount
    slot: int | None  # slot index, or None when slot_ms is given
    slot_ms: float | None
    key: str = ""  # the Zenoh key its records come on (``fuse``); default robot/<name>
    field_of_view_deg: float = 90.0  # half-angle off its facing within which targets are fused
    # half-angle within which it reliably sees a target: a fused track predicted outside every
    # board's is charged no miss (it coasts; robot/coast.py)
    detection_deg: float = DETECTION_DEG
    # `fuse` accepts only records tagged with this secret (outputs/record_auth.py); a path
    # relative to the robot file's folder; "" accepts any record on the key
    auth_key_file: str = ""


@dataclass(frozen=True)
class TriggerSpec:
    period_ms: float = 40.0
    max_range_m: float = 1.0
    sync_margin_ms: float = 0.5
    speed_of_sound_m_s: float = 343.0
    window_ms: float = 0.0  # acquisition window; 0: from the profile (n_samples / rate)


@dataclass(frozen=True)
class RobotSpec:
    name: str
    frame_id: str
    trigger: TriggerSpec
    boards: tuple[BoardSpec, ...]
    origin: str = "robot"
    track: dict = field(default_factory=dict)  # [track] keys over the first board's profile's

    def auth_key_path(self, board: BoardSpec) -> Path | None:
        """The board's key file (relative paths from the robot file's folder), or None."""
        if not board.auth_key_file:
            return None
        path = Path(board.auth_key_file).expanduser()
        origin = Path(self.origin)
        return path if path.is_absolute() or not origin.is_file() else origin.parent / path

    def track_spec(self):
        """The fused tracker's settings: the first board's profile's [track], this file's
        [track] keys over it."""
        from spiel_edge.profile.schema import resolve_profile

        first = self.boards[0]
        base = resolve_profile(first.profile, first.calibration).track
        return replace(base, **self.track) if self.track else base

    def board(self, name: str) -> BoardSpec:
        for b in self.boards:
            if b.name == name:
                return b
        raise ConfigError(f"{self.origin}: no board named {name!r}")


def rotation_from_rpy_deg(rpy) -> np.ndarray:
    return rotation_from_xyzw(quaternion_from_rpy(*(math.radians(v) for v in rpy)))


def rotation_from_xyzw(q) -> np.ndarray:
    x, y, z, w = (float(v) for v in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_problem(r: np.ndarray) -> str | None:
    """Why ``r`` is not a proper rotation (orthonormal, determinant +1), or None."""
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        return "must be a finite 3 x 3 matrix"
    err = float(np.max(np.abs(r.T @ r - np.eye(3))))
    if err > ROTATION_TOLERANCE:
        return f"is not a rotation (R^T R differs from I by {err:.3g})"
    det = float(np.linalg.det(r))
    if abs(det - 1.0) > ROTATION_TOLERANCE:
        return f"is not a rotation (determinant {det:.3g}, a reflection)"
    return None


def load_robot(path: str | Path) -> RobotSpec:
    """Read and check a robot file; ConfigError (one line) on any problem."""
    from spiel_edge.robot import robot_path

    path = robot_path(str(path))
    origin = str(path)
    try:
        if not path.is_file():
            what = "a folder" if path.is_dir() else "not a regular file"
            raise ConfigError(f"{origin}: {what if path.exists() else 'no such robot file'}")
        if path.stat().st_size > MAX_FILE_BYTES:
            raise ConfigError(f"{origin}: a robot file is at most {MAX_FILE_BYTES} bytes")
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{origin}: cannot read robot file: {exc}") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{origin}: not valid TOML: {exc}") from exc
    return robot_from_dict(data, origin=origin)


def robot_from_dict(data: dict, *, origin: str = "robot") -> RobotSpec:
    def fail(msg: str):
        raise ConfigError(f"{origin}: {msg}")

    unknown = set(data) - {"robot", "trigger", "board", "track"}
    if unknown:
        fail(f"unknown section(s) {sorted(unknown)}; known: robot, trigger, board, track")
    track = _track(_table(data.get("track", {}), "[track]", fail), origin)
    head = _table(data.get("robot", {}), "[robot]", fail)
    name = head.get("name", "robot")
    if not isinstance(name, str) or not name.strip():
        fail(f"[robot] name must be a non-empty string, got {name!r}")
    frame_id = head.get("frame_id", "base_link")
    problem = frame_id_problem(frame_id)
    if problem:
        fail(f"robot.frame_id {problem}")
    trigger = _trigger(_table(data.get("trigger", {}), "[trigger]", fail), fail)
    rows = data.get("board")
    if not isinstance(rows, list) or not rows:
        fail("needs at least one [[board]]")
    if len(rows) > MAX_BOARDS:
        fail(f"at most {MAX_BOARDS} boards, got {len(rows)}")
    boards = tuple(_board(i, _table(row, f"board[{i}]", fail), fail) for i, row in enumerate(rows))
    _check_unique(boards, fail)
    spec = RobotSpec(name, frame_id, trigger, boards, origin, track=track)
    from spiel_edge.robot.schedule import Schedule  # slots need the trigger settings

    Schedule.from_robot(spec)  # overlapping slots: ConfigError
    return spec


def _table(value, where: str, fail) -> dict:
    if not isinstance(value, dict):
        fail(f"{where} must be a table")
    return value


def _number(value, where: str, fail, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        fail(f"{where} must be a number, got {value!r}")
    if not lo <= value <= hi:
        fail(f"{where} must be in [{lo:g}, {hi:g}], got {value!r}")
    return float(value)


def _vector(value, where: str, fail, n: int, lo: float, hi: float) -> list[float]:
    if not isinstance(value, list) or len(value) != n:
        fail(f"{where} must be {n} numbers, got {value!r}")
    return [_number(v, where, fail, lo, hi) for v in value]


def _trigger(t: dict, fail) -> TriggerSpec:
    known = {"period_ms", "max_range_m", "sync_margin_ms", "speed_of_sound_m_s", "window_ms"}
    if set(t) - known:
        fail(f"[trigger]: unknown key(s) {sorted(set(t) - known)}; known: {sorted(known)}")
    d = TriggerSpec()
    return TriggerSpec(
        period_ms=_number(t.get("period_ms", d.period_ms), "trigger.period_ms", fail, 1, 10000),
        max_range_m=_number(
            t.get("max_range_m", d.max_range_m), "trigger.max_range_m", fail, 0.05, 20
        ),
        sync_margin_ms=_number(
            t.get("sync_margin_ms", d.sync_margin_ms), "trigger.sync_margin_ms", fail, 0, 100
        ),
        speed_of_sound_m_s=_number(
            t.get("speed_of_sound_m_s", d.speed_of_sound_m_s),
            "trigger.speed_of_sound_m_s",
            fail,
            200,
            2000,
        ),
        window_ms=_number(t.get("window_ms", d.window_ms), "trigger.window_ms", fail, 0, 1000),
    )


def _track(t: dict, origin: str) -> dict:
    """[track]: keys of a profile's [track] (profile/track_section.py), each range-checked."""
    from spiel_edge.profile.track_section import TrackSpec, validate_track

    known = {f.name: f for f in fields(TrackSpec)}
    for key in t:
        if key not in known:
            raise ConfigError(f"{origin}: [track]: unknown key {key!r}; known: {sorted(known)}")
    values = {}
    for key, value in t.items():
        kind = type(getattr(TrackSpec(), key))
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or not math.isfinite(value)
        ):
            raise ConfigError(f"{origin}: track.{key} must be a finite number, got {value!r}")
        if kind is int and value != int(value):
            raise ConfigError(f"{origin}: track.{key} must be an integer, got {value!r}")
        values[key] = kind(value)
    validate_track(replace(TrackSpec(), **values), origin)
    return values


def _board(i: int, b: dict, fail) -> BoardSpec:
    where = f"board[{i}]"
    if set(b) - _BOARD_KEYS:
        fail(
            f"{where}: unknown key(s) {sorted(set(b) - _BOARD_KEYS)}; known: {sorted(_BOARD_KEYS)}"
        )
    name = b.get("name")
    if not isinstance(name, str) or frame_id_problem(name):
        fail(f"{where}.name must be a frame-id-like name (letters, digits, _ . / -), got {name!r}")
    where = f"board {name!r}"
    port = b.get("port", "")
    if not isinstance(port, str):
        fail(f"{where}: port must be a string")
    key = b.get("key", "")
    if not isinstance(key, str):
        fail(f"{where}: key must be a string")
    key = key or f"robot/{name}"
    if problem := publish_key_problem(key):
        fail(f"{where}: key {key!r} {problem}")
    profile = b.get("profile", "spiel-icra23")
    calibration = b.get("calibration", "") or None
    if not isinstance(profile, str) or not (calibration is None or isinstance(calibration, str)):
        fail(f"{where}: profile and calibration must be strings")
    if not profile.strip():
        fail(f"{where}: profile is empty (a profile's name, e.g. spiel-icra23, or its file)")
    translation = _vector(
        b.get("translation_m", [0, 0, 0]), f"{where}.translation_m", fail, 3, -100, 100
    )
    given = [k for k in ("rotation_rpy_deg", "rotation_xyzw", "rotation_matrix") if k in b]
    if len(given) > 1:
        fail(f"{where}: give one of rotation_rpy_deg, rotation_xyzw, rotation_matrix, not {given}")
    if "rotation_xyzw" in b:
        q = _vector(b["rotation_xyzw"], f"{where}.rotation_xyzw", fail, 4, -2, 2)
        norm = math.sqrt(sum(v * v for v in q))
        if abs(norm - 1.0) > ROTATION_TOLERANCE:
            fail(f"{where}.rotation_xyzw is not a rotation: norm {norm:.4g}, must be 1")
        rotation = rotation_from_xyzw([v / norm for v in q])
    elif "rotation_matrix" in b:
        rows = b["rotation_matrix"]
        if not isinstance(rows, list) or len(rows) != 3:
            fail(f"{where}.rotation_matrix must be 3 rows of 3 numbers")
        r = np.array([_vector(row, f"{where}.rotation_matrix", fail, 3, -2, 2) for row in rows])
        problem = rotation_problem(r)
        if problem:
            fail(f"{where}.rotation_matrix {problem}")
        u, _, vt = np.linalg.svd(r)  # the nearest exact rotation
        rotation = u @ vt
    else:
        rpy = _vector(
            b.get("rotation_rpy_deg", [0, 0, 0]), f"{where}.rotation_rpy_deg", fail, 3, -360, 360
        )
        rotation = rotation_from_rpy_deg(rpy)
    slot, slot_ms = b.get("slot"), b.get("slot_ms")
    if slot is not None and slot_ms is not None:
        fail(f"{where}: give slot or slot_ms, not both")
    if slot is not None and (
        isinstance(slot, bool) or not isinstance(slot, int) or not 0 <= slot < MAX_BOARDS
    ):
        fail(f"{where}.slot must be an integer in [0, {MAX_BOARDS - 1}], got {slot!r}")
    if slot is None and slot_ms is None:
        slot = i
    if slot_ms is not None:
        slot_ms = _number(slot_ms, f"{where}.slot_ms", fail, 0, 10000)
    fov = _number(b.get("field_of_view_deg", 90.0), f"{where}.field_of_view_deg", fail, 5, 90)
    seen = _number(b.get("detection_deg", DETECTION_DEG), f"{where}.detection_deg", fail, 5, 90)
    mount = Mount(rotation, np.array(translation) * 1000.0)
    auth = b.get("auth_key_file", "")
    if not isinstance(auth, str):
        fail(f"{where}: auth_key_file must be a string (a file's path)")
    return BoardSpec(
        name, port, profile, calibration, mount, slot, slot_ms, key, fov, seen, auth_key_file=auth
    )


def _check_unique(boards: tuple[BoardSpec, ...], fail) -> None:
    seen_names: set[str] = set()
    seen_ports: dict[str, str] = {}
    for b in boards:
        if b.name in seen_names:
            fail(f"two boards are named {b.name!r}")
        seen_names.add(b.name)
        if b.port:
            key = _port_key(b.port)
            if key in seen_ports:
                fail(f"boards {seen_ports[key]!r} and {b.name!r} are both on port {b.port!r}")
            seen_ports[key] = b.name
    keys: dict[str, str] = {}
    for b in boards:
        if b.key in keys:
            fail(f"boards {keys[b.key]!r} and {b.name!r} both publish on key {b.key!r}")
        keys[b.key] = b.name


def _port_key(port: str) -> str:
    """Ports that name one device compare equal (/dev/x and serial:///dev/x; case of sim)."""
    p = port.strip()
    if p.startswith("serial://"):
        p = p[len("serial://") :]
    if p.startswith("/"):
        with contextlib.suppress(OSError):
            p = str(Path(p).resolve())
    return p  # sim://NAME?options: one URL, one board (the registry's key)
