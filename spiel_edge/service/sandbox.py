"""Will the confined unit see its own program? ``ProtectHome=yes`` hides /home, /root and
/run/user from the service, ``PrivateTmp=yes`` gives it an empty /tmp and /var/tmp: an
ExecStart (or the venv and package behind it) under one of them fails with 203/EXEC or an
ImportError. ``service install`` fixes what it can (ProtectHome=read-only for an install
under /home) and refuses what it cannot (/tmp); ``doctor`` checks the installed unit."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path, PurePosixPath

from spiel_edge.errors import ConfigError
from spiel_edge.service.host_checks import Check

HOME_DIRS = ("/home", "/root", "/run/user")  # ProtectHome=
TMP_DIRS = ("/tmp", "/var/tmp")  # PrivateTmp=
UNIT_FILE = "/etc/systemd/system/spiel-edge.service"


def _under(path: str, roots: tuple[str, ...]) -> bool:
    p = PurePosixPath(path)
    return any(p == PurePosixPath(r) or PurePosixPath(r) in p.parents for r in roots)


def needed_paths(exec_path: str) -> list[str]:
    """What the service reads to start: the program, where it points (its script's
    interpreter), and, when it is this install's, the spiel_edge package itself (an
    editable install's source tree)."""
    out = [exec_path]
    with_links = Path(exec_path)
    try:
        out.append(str(with_links.resolve()))
        head = with_links.read_bytes()[:512].split(b"\n", 1)[0]
        if head.startswith(b"#!"):
            out.append(head[2:].decode(errors="replace").split()[0])
    except (OSError, IndexError, ValueError):  # missing, unreadable, a NUL in the path
        pass
    beside = Path(sys.executable).parent / "spiel-edge"
    if Path(exec_path) == beside:
        import spiel_edge

        out.append(str(Path(spiel_edge.__file__).resolve().parent))
    return list(dict.fromkeys(out))


def hidden(paths: list[str], protect_home: str = "yes") -> tuple[str, str] | None:
    """(path, what hides it) for the first path the unit's sandbox hides, or None."""
    for p in paths:
        if _under(p, TMP_DIRS):
            return p, "PrivateTmp=yes (the service gets an empty /tmp and /var/tmp)"
        if protect_home == "yes" and _under(p, HOME_DIRS):
            return p, "ProtectHome=yes (the service sees no /home, /root or /run/user)"
    return None


def protect_home_for(exec_path: str) -> str:
    """``yes``, or ``read-only`` when the install lives under /home; ConfigError (one line)
    when it lives where the unit cannot see it at all (/tmp)."""
    paths = needed_paths(exec_path)
    found = hidden(paths, "read-only")
    if found:
        raise ConfigError(
            f"service install: {found[0]} lies where the unit cannot see it: {found[1]}; "
            "install spiel-edge elsewhere (e.g. python3 -m venv /opt/spiel-edge && "
            "/opt/spiel-edge/bin/pip install spiel-edge) and pass --exec"
        )
    return "read-only" if hidden(paths, "yes") else "yes"


def unit_settings(text: str) -> dict[str, str]:
    """The [Service] keys of a unit (the last value of each; ExecStart's program word)."""
    out: dict[str, str] = {}
    for line in text.splitlines():
        line = line.strip()
        if "=" in line and not line.startswith(("#", ";", "[")):
            key, value = line.split("=", 1)
            out[key.strip()] = value.strip()
    if "ExecStart" in out:
        word = out["ExecStart"].lstrip("-@:+!")
        out["ExecStart"] = word.split()[0].strip('"') if word.split() else ""
    return out


def check_unit(unit_file: str | Path = UNIT_FILE, analyze: str | None = "auto") -> Check:
    """The installed unit would start: its program visible inside its sandbox, and
    ``systemd-analyze verify`` (where it exists) finds nothing about it."""
    unit_file = Path(unit_file)
    if not unit_file.is_file():
        return Check("unit", True, f"{unit_file}: not installed (nothing to check)")
    try:
        settings = unit_settings(unit_file.read_text(errors="replace"))
    except OSError as exc:
        return Check("unit", False, f"{unit_file}: cannot read it ({exc.strerror})")
    exec_path = settings.get("ExecStart", "")
    paths = needed_paths(exec_path) if exec_path else []
    private_tmp = settings.get("PrivateTmp", "no") in ("yes", "true", "1", "on")
    found = hidden(
        [p for p in paths if private_tmp or not _under(p, TMP_DIRS)],
        settings.get("ProtectHome", "no"),
    )
    fix = (
        "run `sudo spiel-edge service install` again from an install outside /tmp (it sets "
        "ProtectHome=read-only for one under /home)"
    )
    if found:
        return Check("unit", False, f"{unit_file}: {found[0]} is hidden by {found[1]}", fix)
    tool = shutil.which("systemd-analyze") if analyze == "auto" else analyze
    if not tool:
        return Check(
            "unit",
            True,
            f"{unit_file}: its program is visible to it (systemd-analyze not here to verify more)",
        )
    try:
        proc = subprocess.run(
            [tool, "verify", str(unit_file)], capture_output=True, text=True, timeout=60
        )
    except (OSError, subprocess.SubprocessError) as exc:
        return Check("unit", True, f"{unit_file}: systemd-analyze verify did not run ({exc})")
    findings = [line for line in (proc.stdout + proc.stderr).splitlines() if unit_file.name in line]
    if proc.returncode != 0 or findings:
        first = findings[0] if findings else f"exit status {proc.returncode}"
        return Check("unit", False, f"systemd-analyze verify: {first}", fix)
    return Check("unit", True, f"{unit_file}: systemd-analyze verify finds nothing")
