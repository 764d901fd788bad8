"""The service kit: systemd unit, sysusers entry, udev rule and /etc/spiel-edge config.

The texts are rendered here (the wheel carries no data files outside the package), and
``packaging/`` in the repository holds the default rendering; a test keeps them identical.
:func:`plan` is pure; :func:`install` writes a plan under a prefix and never overwrites a
config file the user may have edited.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from spiel_edge.errors import SpielError
from spiel_edge.service.unit_quote import exec_path as quote_exec_path

log = logging.getLogger(__name__)

SERVICE_USER = "spiel-edge"
GROUPS = ("dialout", "plugdev")
DEFAULT_EXEC = "/usr/local/bin/spiel-edge"
CONFIG_DIR = "/etc/spiel-edge"
UNIT_PATH = "etc/systemd/system/spiel-edge.service"
SYSUSERS_PATH = "etc/sysusers.d/spiel-edge.conf"
UDEV_PATH = "etc/udev/rules.d/99-spiel-edge.rules"
ENV_PATH = "etc/spiel-edge/spiel-edge.env"
WATCHDOG_SEC = 10


def usb_ids() -> tuple[tuple[int, int], ...]:
    """The board's USB ids (link/usb_ids.py, or $SPIEL_USB_IDS when set)."""
    from spiel_edge.link.usb_ids import board_usb_ids

    return board_usb_ids()


def render_unit(
    exec_path: str = DEFAULT_EXEC, *, protect_home: str = "yes", allow_ip: tuple[str, ...] = ()
) -> str:
    """The unit; ``exec_path`` quoted per systemd's rules (ConfigError when it cannot be).
    ``protect_home``: ``read-only`` when the install lives under /home (sandbox.py);
    ``allow_ip``: networks beyond localhost the service may reach (IPAddressAllow=)."""
    exec_word = quote_exec_path(exec_path)
    allowed = " ".join(("localhost", *allow_ip))
    return f"""\
# spiel-edge: 3-D ultrasonic echolocation, published headless.
# Installed by `spiel-edge service install`; settings live in {CONFIG_DIR}/spiel-edge.env.
[Unit]
Description=spiel-edge ultrasonic echolocation
After=network-online.target
Wants=network-online.target
# A robot keeps retrying (board unplugged for a while, ...): never give up restarting.
StartLimitIntervalSec=0

[Service]
Type=notify
NotifyAccess=main
User={SERVICE_USER}
Group={SERVICE_USER}
SupplementaryGroups={" ".join(GROUPS)}
# numba compiles the pipeline on first start and caches it here; the install stays read-only.
CacheDirectory=spiel-edge
Environment=NUMBA_CACHE_DIR=/var/cache/spiel-edge/numba
# Recordings (--record /var/lib/spiel-edge/...) go here.
StateDirectory=spiel-edge
Environment=PYTHONUNBUFFERED=1
EnvironmentFile=-{CONFIG_DIR}/spiel-edge.env
ExecStart={exec_word} $SPIEL_VERBOSITY run $SPIEL_RUN_OPTIONS
# READY comes after the pipeline is compiled or loaded from the cache; WATCHDOG on progress.
TimeoutStartSec=180
WatchdogSec={WATCHDOG_SEC}
Restart=on-failure
RestartSec=3
# SIGTERM finalizes the recording and exits; 130/143 are the interrupted-run statuses.
TimeoutStopSec=5
SuccessExitStatus=130 143
# `--realtime 10` in SPIEL_RUN_OPTIONS (docs/robot.md: latency on a loaded computer) may take
# Linux's SCHED_FIFO up to this priority; without the option nothing changes.
LimitRTPRIO=10
# Confinement (docs/security.md; `systemd-analyze security spiel-edge` scores it 1.6, "OK").
# Only what the service needs: the board's serial and USB device nodes, its cache and state
# folders, the journal, and the network on this computer. Widen the network with
# `spiel-edge service install --allow-ip 192.168.1.0/24` or a drop-in (systemctl edit):
# IPAddressAllow=192.168.1.0/24 (Zenoh to other computers, --udp, Foxglove clients).
NoNewPrivileges=yes
CapabilityBoundingSet=
AmbientCapabilities=
UMask=0027
ProtectSystem=strict
ProtectHome={protect_home}
PrivateTmp=yes
PrivateMounts=yes
PrivateIPC=yes
ProtectKernelTunables=yes
ProtectKernelModules=yes
ProtectKernelLogs=yes
ProtectControlGroups=yes
ProtectClock=yes
ProtectHostname=yes
ProtectProc=invisible
DevicePolicy=closed
DeviceAllow=char-ttyACM rw
DeviceAllow=char-ttyUSB rw
DeviceAllow=char-usb_device rw
LockPersonality=yes
RestrictSUIDSGID=yes
RestrictNamespaces=yes
RemoveIPC=yes
KeyringMode=private
# numba compiles to executable memory, so MemoryDenyWriteExecute stays off; realtime stays
# allowed for --realtime (LimitRTPRIO above bounds it).
SystemCallArchitectures=native
SystemCallFilter=@system-service
SystemCallFilter=~@privileged
SystemCallErrorNumber=EPERM
RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6 AF_NETLINK
IPAddressDeny=any
IPAddressAllow={allowed}

[Install]
WantedBy=multi-user.target
"""


def render_sysusers() -> str:
    lines = [f'u {SERVICE_USER} - "spiel-edge sensor driver" /var/lib/spiel-edge']
    lines += [f"m {SERVICE_USER} {group}" for group in GROUPS]
    return (
        "# The unprivileged service user, in the groups that own the board's device nodes.\n"
        + "\n".join(lines)
        + "\n"
    )


def render_udev(ids: tuple[tuple[int, int], ...] | None = None) -> str:
    ids = usb_ids() if ids is None else ids
    out = [
        "# spiel-edge transducer board: group access, stable names, ModemManager kept away.",
        "# /dev/spiel-<serial> names one board; /dev/spiel-0 is the last board plugged in.",
    ]
    for vid, pid in ids:
        match = f'ATTRS{{idVendor}}=="{vid:04x}", ATTRS{{idProduct}}=="{pid:04x}"'
        out += [
            f"# USB {vid:04x}:{pid:04x}",
            f'SUBSYSTEM=="tty", {match}, GROUP="dialout", MODE="0660", ENV{{ID_MM_DEVICE_IGNORE}}="1", SYMLINK+="spiel-0"',
            f'SUBSYSTEM=="tty", {match}, ATTRS{{serial}}=="?*", SYMLINK+="spiel-%s{{serial}}"',
            f'SUBSYSTEM=="usb", ENV{{DEVTYPE}}=="usb_device", {match.replace("ATTRS", "ATTR")}, '
            f'GROUP="plugdev", MODE="0660", ENV{{ID_MM_DEVICE_IGNORE}}="1"',
        ]
    return "\n".join(out) + "\n"


def render_env() -> str:
    return f"""\
# spiel-edge service settings (systemd EnvironmentFile: KEY=VALUE, no shell syntax).
# After editing: sudo systemctl restart spiel-edge. Check with: spiel-edge doctor --config {CONFIG_DIR}

# The board: a device path, a stable udev name, usb://VID:PID[/SERIAL], or sim:// (virtual board).
SPIEL_PORT=/dev/spiel-0
# The board's USB ids for discovery and doctor (hexadecimal VID:PID, comma-separated); the udev
# rule takes them from `sudo SPIEL_USB_IDS=... spiel-edge service install`:
# SPIEL_USB_IDS={",".join(f"{vid:04x}:{pid:04x}" for vid, pid in usb_ids())}

# Options of `spiel-edge run`, split on spaces. Profile: a built-in name or a TOML path
# (copy one here to edit it); calibration: the file `spiel-edge calibrate` writes.
#   --calibration {CONFIG_DIR}/calibration.toml
#   --record /var/lib/spiel-edge/spiel-%Y%m%d-%H%M%S.mcap   (strftime: one file per start)
#   --udp HOST:PORT   --foxglove 127.0.0.1:8765   --zenoh robots/r1/spiel
#   the unit reaches localhost only: other computers (Zenoh --zenoh-connect, --udp) need
#   `service install --allow-ip NETWORK`; --zenoh-auth-key FILE tags records for `fuse`
#   (docs/security.md; ZENOH_CONFIG=FILE on a line of its own for mTLS)
#   ROS 2 (docs/ros2.md): --record-profile ros2   --zenoh-encoding cdr   --frame-id spiel
#   the sensor's pose on the robot: [frame] in the profile, or --parent-frame base_link
#   --translation-m 0.10,0,0.25 --rotation-rpy-deg 0,0,90   (metres, degrees)
#   low latency on a loaded computer (docs/robot.md): --realtime 10 (Linux SCHED_FIFO once the
#   kernels are ready; the unit's LimitRTPRIO=10 allows it)
# NDJSON goes to /dev/null here: on stdout it would fill the journal at the frame rate.
SPIEL_RUN_OPTIONS=--profile spiel-icra23 --output /dev/null --udp 127.0.0.1:9870

# -v for info logs, -vv for debug.
SPIEL_VERBOSITY=-v
"""


IP_KEYWORDS = ("any", "localhost", "link-local", "multicast")  # systemd.resource-control(5)


def check_allow_ip(text: str) -> str:
    """An IPAddressAllow= entry: an address, a network (CIDR) or one of systemd's keywords."""
    import ipaddress

    from spiel_edge.errors import ConfigError

    if text in IP_KEYWORDS:
        return text
    try:
        return str(ipaddress.ip_network(text, strict=False))
    except ValueError:
        raise ConfigError(
            f"--allow-ip {text!r}: an address or network (192.168.1.0/24) or one of "
            f"{', '.join(IP_KEYWORDS)}"
        ) from None


@dataclass(frozen=True)
class KitFile:
    path: str  # relative to the prefix
    text: str
    config: bool = False  # the user's to edit: never overwritten


def plan(
    exec_path: str = DEFAULT_EXEC, *, protect_home: str = "yes", allow_ip: tuple[str, ...] = ()
) -> list[KitFile]:
    return [
        KitFile(UNIT_PATH, render_unit(exec_path, protect_home=protect_home, allow_ip=allow_ip)),
        KitFile(SYSUSERS_PATH, render_sysusers()),
        KitFile(UDEV_PATH, render_udev()),
        KitFile(ENV_PATH, render_env(), config=True),
    ]


def default_exec() -> str:
    """The spiel-edge script beside this interpreter (a venv install), else on PATH."""
    beside = Path(sys.executable).parent / "spiel-edge"
    if beside.exists():
        return str(beside)
    return shutil.which("spiel-edge") or DEFAULT_EXEC


def install(files: list[KitFile], prefix: str | Path = "/") -> list[tuple[Path, str]]:
    """Write ``files`` under ``prefix``; returns (path, "written" | "kept" | "unchanged")."""
    done = []
    for kit_file in files:
        target = Path(prefix) / kit_file.path
        if target.exists() and (kit_file.config or target.read_text() == kit_file.text):
            done.append((target, "kept" if target.read_text() != kit_file.text else "unchanged"))
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(kit_file.text)
        done.append((target, "written"))
    return done


CACHE_PATH = "var/cache/spiel-edge/numba"  # the unit's NUMBA_CACHE_DIR, relative to the prefix


def warm_cache(exec_path: str, prefix: str | Path = "/", timeout_s: float = 900.0) -> dict:
    """Run ``spiel-edge warmup`` with the unit's NUMBA_CACHE_DIR (under ``prefix``), so the
    service's first start loads compiled kernels; returns the warm-up's JSON report. systemd
    hands CacheDirectory= to the service user when the unit starts."""
    cache = Path(prefix) / CACHE_PATH
    cache.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    try:
        out = subprocess.run(
            [exec_path, "warmup", "--json"],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout_s,
            check=True,
        )
        return json.loads(out.stdout.strip().splitlines()[-1])
    except (OSError, subprocess.SubprocessError, ValueError, IndexError) as exc:
        raise SpielError(f"warm-up with {exec_path} failed: {exc}") from exc


def next_steps(prefix: str | Path = "/") -> list[str]:
    """Commands to run after install (as root); spelled out, never run for the user."""
    steps = [
        "systemd-sysusers                      # creates the spiel-edge user and its groups",
        "udevadm control --reload && udevadm trigger --subsystem-match=tty --subsystem-match=usb",
        "systemctl daemon-reload",
        "systemctl enable --now spiel-edge",
        "journalctl -u spiel-edge -f           # logs; `spiel-edge doctor` if it does not start",
    ]
    if Path(prefix).resolve() != Path("/"):
        steps.insert(0, f"# files were written under {prefix}: copy them to / first")
    return steps


# Where each kit file sits in the repository's packaging/ folder.
PACKAGING_LAYOUT = {
    UNIT_PATH: "systemd/spiel-edge.service",
    SYSUSERS_PATH: "sysusers/spiel-edge.conf",
    UDEV_PATH: "udev/99-spiel-edge.rules",
    ENV_PATH: "etc/spiel-edge/spiel-edge.env",
}


def packaging_files() -> dict[str, str]:
    """packaging/-relative path -> text, with the default ExecStart."""
    return {PACKAGING_LAYOUT[f.path]: f.text for f in plan(DEFAULT_EXEC)}


def write_packaging(root: str | Path = "packaging") -> None:
    for rel, text in packaging_files().items():
        target = Path(root) / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text)
