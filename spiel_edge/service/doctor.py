"""``spiel-edge doctor``: what stands between this machine and a running service.

Each check is a function returning a :class:`Check` with a fix to try when it fails; every
environment fact (device list, /dev, groups, /proc, paths) is a parameter, so tests feed
their own. :func:`run_checks` runs them all with the real machine's facts.
"""

from __future__ import annotations

import logging
import shlex
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from spiel_edge.errors import SpielError
from spiel_edge.safety.limits import read_input_text
from spiel_edge.service.host_checks import (
    Check,
    check_board,
    check_device_access,
    check_groups,
    check_modemmanager,
    check_symlinks,
    installed_udev_rule,
    modemmanager_running,
    user_groups,
)
from spiel_edge.service.sandbox import check_unit

log = logging.getLogger(__name__)

CONFIG_DIR = "/etc/spiel-edge"


# -- configuration -------------------------------------------------------------------------


def read_env_file(path: str | Path) -> dict[str, str]:
    """KEY=VALUE lines as systemd's EnvironmentFile= reads them (comments, optional quotes)."""
    values = {}
    for line in read_input_text(Path(path), "env").splitlines():
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
    profile: str | None = None,
    calibration: str | None = None,
    config_dir: str | Path = CONFIG_DIR,
    rejects: Callable[[dict[str, str]], str | None] | None = None,
) -> Check:
    """The profile and calibration the service would use (from config_dir's env file unless
    given), loaded and validated; ``rejects`` (cli/doctor.py's ``service_rejects``: run's own
    option parser, passed in because the command line sits above this package) judges the env
    file's run options."""
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
    if origin != "defaults" and rejects is not None:
        problem = rejects(read_env_file(env_file))
        if problem:
            return Check(
                "config",
                False,
                f"{env_file}: {problem}",
                "fix SPIEL_RUN_OPTIONS / SPIEL_PORT; `spiel-edge run --help` lists the options",
            )
    return Check("config", True, f"profile {loaded.name!r}{extra} is valid ({origin})")


# -- model ---------------------------------------------------------------------------------


def check_model(path: str | Path | None = None, method: str = "auto") -> Check:
    if method == "geometric":
        return Check("model", True, "not used: the profile asks for geometric association")
    try:
        from spiel_edge.pipeline.learned.associate_onnx import default_model_path, load_session
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
    from spiel_edge.runtime.warmup import cache_dir

    found = cache_dir()
    return None if found is None else Path(found)


def check_numba_cache_dir(path: Path | None) -> Check:
    fix = (
        "set NUMBA_CACHE_DIR to a folder this user can write (the unit uses "
        "/var/cache/spiel-edge/numba with CacheDirectory=spiel-edge)"
    )
    from spiel_edge._kernel_cache import cache_dir_problem

    if problem := cache_dir_problem():
        return Check("numba cache", False, problem, fix)
    if path is None:
        return Check("numba cache", False, "numba finds no writable cache location", fix)
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".doctor-"):
            pass
    except OSError as exc:
        return Check("numba cache", False, f"{path} is not writable: {exc}", fix)
    from spiel_edge import _shipped

    shipped = _shipped.status()
    where = (
        "prebuilt kernels in use"
        if shipped["active"]
        else f"no prebuilt kernels: {shipped['reason']}"
    )
    return Check("numba cache", True, f"{path} is writable ({where})")


def pipeline_dispatchers() -> list[Any]:
    """The pipeline's cached numba kernels (the finder warm-up and bench use too)."""
    from spiel_edge.runtime.warmup import pipeline_kernels

    return list(pipeline_kernels().values())


def kernel_cache_counts(dispatchers: Iterable[Any]) -> tuple[int, int]:
    """(signatures loaded from the cache, signatures compiled) over ``dispatchers``."""
    hits = sum(sum(d.stats.cache_hits.values()) for d in dispatchers)
    misses = sum(sum(d.stats.cache_misses.values()) for d in dispatchers)
    return hits, misses


def warm_pipeline() -> float:
    """Run every kernel once (compile or cache load); seconds taken."""
    from spiel_edge.runtime.warmup import warmup

    return float(warmup(isolate=False)["seconds"])  # here: doctor counts this process's kernels


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


def check_link(port: str) -> Check:
    """The board at ``port`` answers HELLO and CONFIG_STATUS: the protocol version and link
    max_payload negotiated, and whether a config is stored (PROTOCOL.md 6.2, 9)."""
    from spiel_edge.device import DeviceSession

    session = DeviceSession(port, reconnect=False)
    try:
        hello = session.open()
        status = session.config_status() if hello.capabilities & 0x02 else None
    except SpielError as exc:
        return Check(
            "board link",
            False,
            f"{port}: {exc}",
            "check the port and that nothing else holds it open (`spiel-edge service stop`)",
        )
    finally:
        session.close()
    stored = (
        "no config capability"
        if status is None
        else "no config stored (factory defaults)"
        if status.active_slot == 0xFF
        else f"config in slot {status.active_slot}"
    )
    return Check(
        "board link",
        True,
        f"{port}: board {hello.serial} firmware {hello.firmware_version}, protocol "
        f"{hello.protocol_version} (board {hello.min_version}-{hello.max_version}), "
        f"max_payload {session.max_payload}, {hello.n_channels} channels, {stored}",
    )


HOST_DEVICE_CHECKS = ("board", "device access", "stable names", "groups", "ModemManager")
PTY_MAJORS = range(136, 144)  # Unix98 pseudo-terminal slaves (/dev/pts/N)


def port_kind(port: str) -> str | None:
    """``virtual board`` for a sim:// URL, ``pseudo-terminal`` for a pty (a board served by
    `spiel-edge simulate --pty` or the posix firmware), None for anything else (a USB board)."""
    import os
    import stat

    if port.lower().startswith("sim:"):
        return "virtual board"
    path = port.removeprefix("serial://").split("?", 1)[0]
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    if stat.S_ISCHR(st.st_mode) and os.major(st.st_rdev) in PTY_MAJORS:
        return "pseudo-terminal"
    return None


def _not_needed(check: Check, port: str, kind: str) -> Check:
    """A USB board's host check, passed for a board on a pty or the virtual board: it answered,
    and no USB id, udev name, group or ModemManager stands between it and spiel-edge."""
    if check.ok or check.name not in HOST_DEVICE_CHECKS:
        return check
    return Check(
        check.name,
        True,
        f"not needed for {port} (a {kind}, answering); for a USB board: {check.detail}",
    )


def run_checks(
    profile: str | None = None,
    calibration: str | None = None,
    config_dir: str | Path = CONFIG_DIR,
    skip_numba: bool = False,
    port: str | None = None,
    rejects: Callable[[dict[str, str]], str | None] | None = None,
) -> list[Check]:
    from spiel_edge.link.discover import find_boards
    from spiel_edge.link.usb_ids import board_usb_ids

    ids = board_usb_ids()  # the same ids as discovery and the udev rule
    boards = find_boards(ids)
    nodes = [b.url for b in boards if b.url.startswith("/dev/")]
    checks = [
        check_board(boards, ids),
        check_device_access(nodes),
        check_symlinks("/dev"),
        check_groups(*user_groups()),
        check_modemmanager(modemmanager_running(), installed_udev_rule(ids)),
        check_config(profile, calibration, config_dir, rejects),
        check_model(),
        check_unit(),  # the installed unit would start (sandbox.py)
    ]
    if port:
        link = check_link(port)
        checks.insert(1, link)
        kind = port_kind(port)
        if link.ok and kind is not None:  # a working board that no USB or udev check concerns
            checks = [_not_needed(c, port, kind) for c in checks]
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
