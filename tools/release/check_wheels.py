"""Check that every runtime dependency resolves to binary wheels on the boards we support.

    .venv/bin/python -m tools.release.check_wheels [--python 3.10 3.12] [--arch x86_64 aarch64]
                                           [--glibc 2_35] [--extra zenoh ...]

For each (Python, architecture) pip resolves the [project] dependencies of pyproject.toml with
``--dry-run --only-binary=:all: --python-version V --platform manylinux_G_ARCH`` (no install, no
build: a dependency that ships only an sdist fails to resolve) and lists what it picked.
glibc 2.35 is Ubuntu 22.04 (ROS 2 Humble, JetPack 6); Raspberry Pi OS bookworm has 2.36.
Needs the package index (PyPI); prints one JSON line per target, exits 1 if any fails.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from spiel_edge.compat import tomllib

ROOT = Path(__file__).resolve().parents[2]


def requirements(extras: list[str]) -> list[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"])
    for extra in extras:
        reqs += project["optional-dependencies"][extra]
    return reqs


def for_python(reqs: list[str], python: str) -> list[str]:
    """The requirements whose environment markers hold on ``python`` (pip would evaluate them
    for the interpreter running it, e.g. drop tomli's ``python_version < '3.11'``)."""
    try:
        from packaging.requirements import Requirement
    except ImportError:  # pragma: no cover - pip always vendors it
        from pip._vendor.packaging.requirements import Requirement
    out = []
    for text in reqs:
        req = Requirement(text)
        env = {"python_version": python, "python_full_version": f"{python}.0"}
        if req.marker is None or req.marker.evaluate(env):
            req.marker = None
            out.append(str(req))
    return out


def resolve(reqs: list[str], python: str, arch: str, glibc: str) -> dict:
    platform = f"manylinux_{glibc}_{arch}"
    newest = int(glibc.split("_")[1])
    # pip does not widen an explicit --platform: list every manylinux tag the board accepts
    tags = [f"manylinux_2_{minor}_{arch}" for minor in range(newest, 16, -1)]
    tags += [f"manylinux2014_{arch}"]
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "report.json"
        cmd = [sys.executable, "-m", "pip", "install", "--dry-run", "--quiet", "--ignore-installed"]
        cmd += ["--only-binary=:all:", "--python-version", python]
        cmd += [arg for tag in tags for arg in ("--platform", tag)]
        cmd += ["--target", str(Path(tmp) / "target"), "--report", str(report)]
        cmd += for_python(reqs, python)
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
        result: dict = {"python": python, "platform": platform, "ok": proc.returncode == 0}
        if proc.returncode != 0:
            lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("ERROR")]
            result["error"] = lines[-3:] or proc.stderr.strip().splitlines()[-3:]
            return result
        installs = json.loads(report.read_text())["install"]
    picked = {}
    for item in installs:
        url = item["download_info"]["url"]
        picked[item["metadata"]["name"]] = url.rsplit("/", 1)[-1]
    result["wheels"] = dict(sorted(picked.items()))
    result["ok"] = all(name.endswith(".whl") for name in picked.values())
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--python", nargs="+", default=["3.10", "3.12"])
    ap.add_argument("--arch", nargs="+", default=["x86_64", "aarch64"])
    ap.add_argument("--glibc", default="2_35", help="manylinux glibc version, e.g. 2_35")
    ap.add_argument("--extra", nargs="*", default=[], help="optional extras to include")
    args = ap.parse_args(argv)
    reqs = requirements(args.extra)
    failed = 0
    for python in args.python:
        for arch in args.arch:
            result = resolve(reqs, python, arch, args.glibc)
            failed += not result["ok"]
            print(json.dumps(result), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
