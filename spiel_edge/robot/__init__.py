"""Several boards on one robot: the robot description (description.py), trigger slots and
cross-talk marking (schedule.py), per-board clocks (clock.py), fusion in ``base_link``
(fusion.py), serving every board from one process (serve.py) and fusing boards published on
Zenoh (zenoh_fuse.py). See docs/robot.md."""

from pathlib import Path

BUILTIN_ROBOTS = Path(__file__).parent / "builtin"


def robot_path(name_or_path: str) -> Path:
    """A robot file by path, or a built-in robot by name (``virtual-4``)."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists() or "/" in name_or_path:
        return p
    return BUILTIN_ROBOTS / f"{name_or_path}.toml"
