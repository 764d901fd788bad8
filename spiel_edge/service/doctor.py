"""``spiel-edge doctor``: what stands between this machine and a running service.

Each check is a function returning a :class:`Check` with a fix to try when it fails; every
environment fact (device list, /dev, groups, /proc, paths) is a parameter, so tests feed
their own. :func:`run_checks` runs them all with the real machine's facts.
"""

from __future__ import annotations

import grp
import logging
import os
import pwd
import shlex
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from spiel_edge.errors import SpielError

log = logging.getLogger(__name__)

UDEV_RULE_DIRS = (
    "/etc/udev/rules.d",
    "/run/udev/rules.d",
    "/usr/lib/udev/rules.d",
    "/lib/udev/rules.d",
)
GROUPS = ("dialout", "plugdev")
CONFIG_DIR = "/etc/spiel-edge"


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
    listed = ", ".join(f"{b.url} (serial {b.serial or '?'})" for b in boards)
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


# -- configuration -------------------------------------------------------------------------


def read_env_file(path: str | Path) -> dict[str, str]:
    """KEY=VALUE lines as systemd's EnvironmentFile= reads them (comments, optional quotes)."""
    values = {}
    for line in Path(path).read_text().splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";")) or "=" not in line:
            continue
        key, value = line.split("=", 1)
        value = value.strip()
        if len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
            value = value[1:-1]
        values[key.strip()] = value
    return values


def run_options(env: dict[str, str]) -> tuple[str, str | None]:
    """(profile, calibration) named in SPIEL_RUN_OPTIONS, with run's defaults."""
    args = shlex.split(env.get("SPIEL_RUN_OPTIONS", ""))
    found: dict[str, str] = {}
    for i, arg in enumerate(args):
        for name in ("--profile", "--calibration"):
            if arg == name and i + 1 < len(args):
                found[name] = args[i + 1]
            elif arg.startswith(name + "="):
                found[name] = arg.split("=", 1)[1]
    return found.get("--profile", "spiel-icra23"), found.get("--calibration")


def check_config(
    profile: str | None = None, calibration: str | None = None, config_dir: str | Path = CONFIG_DIR
) -> Check:
    """The profile and calibration the service would use (from config_dir's env file unless
    given), loaded and validated."""
    from spiel_edge.profile.schema import resolve_profile

    env_file = Path(config_dir) / "spiel-edge.env"
    origin = "defaults"
    if profile is None and env_file.is_file():
        try:
            profile, calibration = run_options(read_env_file(env_file))
        except (OSError, ValueError) as exc:
            return Check(
                "config",
                False,
                f"{env_file}: {exc}",
                "fix the file; compare with `spiel-edge service show env`",
            )
        origin = str(env_file)
    profile = profile or "spiel-icra23"
    try:
        loaded = resolve_profile(profile, calibration)
    except SpielError as exc:
        return Check(
            "config",
            False,
            str(exc),
            "fix the named key or file; the built-in profiles are in "
            "spiel_edge/profile/builtin/ for comparison",
        )
    extra = f" + calibration {calibration}" if calibration else ""
    return Check("config", True, f"profile {loaded.name!r}{extra} is valid ({origin})")


# -- model ---------------------------------------------------------------------------------


def check_model(path: str | Path | None = None, method: str = "auto") -> Check:
    if method == "geometric":
        return Check("model", True, "not used: the profile asks for geometric association")
    try:
        from spiel_edge.pipeline.associate_onnx import default_model_path, load_session
    except ImportError as exc:
        return Check(
            "model",
            False,
            f"learned association is not in this install ({exc})",
            "reinstall spiel-edge; geometric association is used meanwhile",
        )
    path = Path(path) if path is not None else default_model_path()
    try:
        load_session(path)
    except (SpielError, ImportError) as exc:
        return Check(
            "model",
            False,
            f"{exc}; geometric association is used instead",
            "reinstall spiel-edge (the package ships the model), or set [associate] method = "
            '"geometric" in the profile to use geometry on purpose',
        )
    return Check("model", True, f"{path} loads in onnxruntime")


# -- numba ---------------------------------------------------------------------------------


def numba_cache_dir() -> Path | None:
    """Where numba caches the pipeline's kernels in this environment (None: nowhere usable)."""
    try:
        from spiel_edge.pipeline import detect
    except RuntimeError as exc:  # numba raises at import when no cache location is writable
        log.debug("numba cache: %s", exc)
        return None
    return Path(detect._detect_kernel._cache._cache_path)


def check_numba_cache_dir(path: Path | None) -> Check:
    fix = (
        "set NUMBA_CACHE_DIR to a folder this user can write (the unit uses "
        "/var/cache/spiel-edge/numba with CacheDirectory=spiel-edge)"
    )
    if path is None:
        return Check("numba cache", False, "numba finds no writable cache location", fix)
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".doctor-"):
            pass
    except OSError as exc:
        return Check("numba cache", False, f"{path} is not writable: {exc}", fix)
    return Check("numba cache", True, f"{path} is writable")


def pipeline_dispatchers() -> list[Any]:
    """The pipeline's cached numba kernels (module-level dispatchers with a cache)."""
    import importlib
    import pkgutil

    import spiel_edge.pipeline as package

    found = []
    for info in pkgutil.iter_modules(package.__path__):
        try:
            module = importlib.import_module(f"{package.__name__}.{info.name}")
        except ImportError:
            continue
        found += [
            obj
            for obj in vars(module).values()
            if getattr(obj, "_cache", None) is not None
            and hasattr(obj, "stats")
            and getattr(obj, "__module__", "") == module.__name__
        ]
    return found


def kernel_cache_counts(dispatchers: Iterable[Any]) -> tuple[int, int]:
    """(signatures loaded from the cache, signatures compiled) over ``dispatchers``."""
    hits = sum(sum(d.stats.cache_hits.values()) for d in dispatchers)
    misses = sum(sum(d.stats.cache_misses.values()) for d in dispatchers)
    return hits, misses


def warm_pipeline() -> float:
    """Run the pipeline once on a vendored acquisition; seconds taken (compile or cache load)."""
    from spiel_edge.data import load_subset
    from spiel_edge.pipeline.associate import GeometricAssociator
    from spiel_edge.pipeline.run import Pipeline
    from spiel_edge.profile.schema import load_profile

    subset = load_subset()
    profile = load_profile("spiel-icra23")
    start = time.perf_counter()
    Pipeline(profile, GeometricAssociator(profile)).process(subset.frames[0], subset.backgrounds[0])
    return time.perf_counter() - start


def check_numba_kernels(warm: Callable[[], float], counts: Callable[[], tuple[int, int]]) -> Check:
    try:
        seconds = warm()
    except Exception as exc:  # a kernel that fails to compile must show up here, not crash doctor
        return Check(
            "numba kernels",
            False,
            f"the pipeline does not run: {type(exc).__name__}: {exc}",
            "reinstall spiel-edge with a numba/numpy pair it supports",
        )
    hits, misses = counts()
    if misses == 0:
        return Check(
            "numba kernels",
            True,
            f"{hits} kernel(s) loaded from the cache; first acquisition took {seconds:.2f} s",
        )
    return Check(
        "numba kernels",
        True,
        f"compiled {misses} kernel(s) in {seconds:.1f} s (not cached yet; the next "
        f"start loads them) and loaded {hits} from the cache",
    )


# -- all -----------------------------------------------------------------------------------


def run_checks(
    profile: str | None = None,
    calibration: str | None = None,
    config_dir: str | Path = CONFIG_DIR,
    skip_numba: bool = False,
) -> list[Check]:
    from spiel_edge.link.discover import BOARD_USB_IDS, find_boards

    boards = find_boards(BOARD_USB_IDS)
    nodes = [b.url for b in boards if b.url.startswith("/dev/")]
    checks = [
        check_board(boards, BOARD_USB_IDS),
        check_device_access(nodes),
        check_symlinks("/dev"),
        check_groups(*user_groups()),
        check_modemmanager(modemmanager_running(), installed_udev_rule(BOARD_USB_IDS)),
        check_config(profile, calibration, config_dir),
        check_model(),
    ]
    if not skip_numba:
        cache = numba_cache_dir()
        checks.append(check_numba_cache_dir(cache))
        if cache is not None:
            checks.append(
                check_numba_kernels(
                    warm_pipeline, lambda: kernel_cache_counts(pipeline_dispatchers())
                )
            )
    return checks
