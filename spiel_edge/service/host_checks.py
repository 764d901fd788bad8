"""The doctor's checks of the host: the board's nodes and USB ids, access rights, the udev
names, group membership and ModemManager. Every environment fact is a parameter."""

from __future__ import annotations

import grp
import os
import pwd
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from spiel_edge.safety.guard import escape

UDEV_RULE_DIRS = (
    "/etc/udev/rules.d",
    "/run/udev/rules.d",
    "/usr/lib/udev/rules.d",
    "/lib/udev/rules.d",
)
GROUPS = ("dialout", "plugdev")


@dataclass(frozen=True)
class Check:
    name: str
    ok: bool
    detail: str
    fix: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


# -- device --------------------------------------------------------------------------------


def check_board(boards: Sequence[Any], ids: Iterable[tuple[int, int]]) -> Check:
    """``boards``: LinkIdentity-like objects (url, vid, pid, serial) found by VID/PID."""
    wanted = ", ".join(f"{v:04x}:{p:04x}" for v, p in ids)
    if not boards:
        return Check(
            "board",
            False,
            f"no board with USB id {wanted} found",
            "plug the board in and check `lsusb`; a charge-only cable or an unpowered hub also hide it",
        )
    listed = ", ".join(f"{escape(b.url)} (serial {escape(b.serial or '?')})" for b in boards)
    return Check("board", True, f"found {listed}")


def check_device_access(
    paths: Sequence[str], access: Callable[[str, int], bool] = os.access
) -> Check:
    """Read/write permission on each device node (symlinks followed)."""
    if not paths:
        return Check(
            "device access", True, "no serial device node to check (no board, or USB bulk only)"
        )
    denied = [p for p in paths if not access(p, os.R_OK | os.W_OK)]
    if denied:
        return Check(
            "device access",
            False,
            f"no read/write access to {', '.join(denied)}",
            "install the udev rule (`spiel-edge service install`) and join the dialout group: "
            "sudo usermod -aG dialout,plugdev $USER, then log in again",
        )
    return Check("device access", True, f"read/write on {', '.join(paths)}")


def check_symlinks(dev_dir: str | Path = "/dev") -> Check:
    links = sorted(Path(dev_dir).glob("spiel-*"))
    if not links:
        return Check(
            "stable names",
            False,
            f"no {dev_dir}/spiel-* symlink",
            "install the udev rule: sudo spiel-edge service install, then "
            "sudo udevadm control --reload && sudo udevadm trigger; replug the board",
        )
    broken = [str(p) for p in links if not p.exists()]
    if broken:
        return Check("stable names", False, f"dangling: {', '.join(broken)}", "replug the board")
    return Check("stable names", True, ", ".join(f"{p} -> {os.path.realpath(p)}" for p in links))


def check_groups(
    user: str, process_groups: set[str], member_of: set[str], is_root: bool = False
) -> Check:
    """``process_groups``: this session's groups; ``member_of``: the group database's view."""
    if is_root:
        return Check("groups", True, "running as root (the service runs as its own user)")
    missing = [g for g in GROUPS if g not in process_groups]
    if not missing:
        return Check("groups", True, f"{user} is in {', '.join(GROUPS)}")
    stale = [g for g in missing if g in member_of]
    if stale and stale == missing:
        return Check(
            "groups",
            False,
            f"{user} was added to {', '.join(stale)} but this session predates it",
            "log out and in again (or reboot)",
        )
    return Check(
        "groups",
        False,
        f"{user} is not in {', '.join(missing)}",
        f"sudo usermod -aG {','.join(missing)} {user}, then log in again",
    )


def user_groups() -> tuple[str, set[str], set[str], bool]:
    """(user, this process's group names, the group database's names for the user, root?)."""
    user = pwd.getpwuid(os.getuid()).pw_name
    process = {_group_name(g) for g in os.getgroups()} | {_group_name(os.getgid())}
    member = {g.gr_name for g in grp.getgrall() if user in g.gr_mem}
    return user, process, member, os.geteuid() == 0


def _group_name(gid: int) -> str:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


# -- ModemManager --------------------------------------------------------------------------


def modemmanager_running(proc: str | Path = "/proc") -> bool:
    for comm in Path(proc).glob("[0-9]*/comm"):
        try:
            if comm.read_text().strip() == "ModemManager":
                return True
        except OSError:  # the process ended while we looked
            continue
    return False


def installed_udev_rule(
    ids: Iterable[tuple[int, int]], dirs: Iterable[str | Path] = UDEV_RULE_DIRS
) -> Path | None:
    """A rules file that names the board's vendor id and sets ID_MM_DEVICE_IGNORE."""
    vendors = {f'"{v:04x}"' for v, _ in ids}
    for folder in dirs:
        for path in sorted(Path(folder).glob("*.rules")):
            try:
                text = path.read_text().lower()
            except OSError:
                continue
            if "id_mm_device_ignore" in text and any(v in text for v in vendors):
                return path
    return None


def check_modemmanager(running: bool, rule: Path | None) -> Check:
    if not running:
        return Check("ModemManager", True, "not running")
    if rule is not None:
        return Check("ModemManager", True, f"running; told to ignore the board by {rule}")
    return Check(
        "ModemManager",
        False,
        "running and may probe the board's ttyACM port (garbled first seconds, busy port)",
        "install the udev rule (`sudo spiel-edge service install`), or "
        "sudo systemctl disable --now ModemManager if this robot has no modem",
    )
