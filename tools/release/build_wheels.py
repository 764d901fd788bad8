"""Build release wheels that carry the compiled kernels (no compile at a user's first start).

    python -m tools.release.build_wheels [--python /usr/bin/python3.11 ...] [--out dist]
        [--work /var/tmp/spiel-release] [--skip-verify]
    sudo python -m tools.release.build_wheels --arch aarch64 [--work /var/tmp/spiel-aarch64]

For each interpreter (x86_64: the ``--python`` ones here; aarch64: the Debian arm64 root of
``aarch64_smoke.sh``, natively under qemu-user):

1. the pure wheel of the checkout (``pip wheel --no-deps``);
2. a fresh venv with it installed; every kernel compiled there for a generic CPU of the
   architecture (``SPIEL_EDGE_KERNELS_OUT``: ``spiel-edge warmup``'s steps write numba's
   cache files in the packages' layout; ``NUMBA_CPU_NAME=generic``);
3. those files and ``manifest.json`` (Python, machine, numba, llvmlite, CPU, SHA-256 of each
   file) added under ``spiel_edge/_kernels/`` and the wheel re-tagged
   ``cpXY-cpXY-<numba's own manylinux tag>`` (the kernels are machine code for that Python
   and numba);
4. checked (unless ``--skip-verify``): installed in another fresh venv, its package folder
   made read-only and owned by root, then ``spiel-edge run --port sim:// --frames 50`` as
   user nobody with an empty NUMBA_CACHE_DIR and ``SPIEL_EDGE_NO_COMPILE=1`` (a kernel not in
   the wheel is an error): the seconds to the first record, and the records kept beside the
   wheel (``<wheel>.sim50.ndjson``) to compare architectures with
   ``python -m tools.compare_ndjson_positions``.

Prints one JSON line per wheel. Needs the package index for the dependencies. Not in CI.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tools.release.wheel_files import KERNELS, manifest, package, platform_tag  # noqa: F401

REPO = Path(__file__).resolve().parents[2]
FRAMES = 50
SIM = "sim://"


class Runner:
    """Runs commands on the host, or in the arm64 root by chroot (paths given as host paths)."""

    def __init__(self, root: Path | None = None):
        self.root = root

    def inside(self, path: Path) -> str:
        if self.root is None:
            return str(path)
        # not resolved: a venv's python links to /usr/bin/python3 *inside* the root
        return "/" + str(Path(os.path.abspath(path)).relative_to(os.path.abspath(self.root)))

    def run(self, cmd: list[str], env: dict | None = None, user: str | None = None, **kw):
        env = {"PATH": "/usr/bin:/bin", "HOME": "/root", **(env or {})}
        prefix = []
        if user is not None:
            prefix = ["setpriv", "--reuid", user, "--regid", user, "--clear-groups", "--"]
        if self.root is not None:
            cert = (
                {"PIP_CERT": "/etc/ssl/host-ca.crt"}
                if (self.root / "etc/ssl/host-ca.crt").exists()
                else {}
            )
            env = {**env, **cert, "PIP_DEFAULT_TIMEOUT": "180"}
            argv = ["chroot", str(self.root), *prefix, "/usr/bin/env", "-i"]
            argv += [f"{k}={v}" for k, v in env.items()] + cmd
            return subprocess.run(argv, **kw)
        passed = ("PIP_", "SSL_", "REQUESTS_CA_BUNDLE", "HTTP_PROXY", "HTTPS_PROXY", "NO_PROXY")
        full = {**{k: v for k, v in os.environ.items() if k.upper().startswith(passed)}, **env}
        return subprocess.run([*prefix, *cmd], env=full, **kw)


def step(text: str) -> None:
    print(f"== [{time.strftime('%H:%M:%S')}] {text}", file=sys.stderr, flush=True)


def pure_wheel(runner: Runner, python: str, work: Path) -> Path:
    """The checkout's wheel, built by ``python`` (under the root: from a copy of the tree)."""
    src = work / "src"
    shutil.rmtree(src, ignore_errors=True)
    ignore = shutil.ignore_patterns(
        ".git", ".venv", "__pycache__", "*.egg-info", "build", "dist", "_kernels"
    )
    shutil.copytree(REPO, src, ignore=ignore)
    out = work / "pure"
    shutil.rmtree(out, ignore_errors=True)
    venv = work / "buildenv"
    if not (venv / "bin/python").exists():
        runner.run([python, "-m", "venv", runner.inside(venv)], check=True)
    vpy = runner.inside(venv / "bin/python")
    runner.run([vpy, "-m", "pip", "install", "-q", "setuptools>=68", "wheel"], check=True)
    runner.run(
        [
            vpy,
            "-m",
            "pip",
            "wheel",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "-w",
            runner.inside(out),
            runner.inside(src),
        ],
        check=True,
    )
    (wheel,) = out.glob("spiel_edge-*.whl")
    return wheel


def fresh_venv(runner: Runner, python: str, path: Path, wheel: Path) -> str:
    shutil.rmtree(path, ignore_errors=True)
    runner.run([python, "-m", "venv", runner.inside(path)], check=True)
    vpy = runner.inside(path / "bin/python")
    runner.run(
        [vpy, "-m", "pip", "install", "-q", "--only-binary=:all:", runner.inside(wheel)],
        check=True,
    )
    return vpy


def compile_kernels(runner: Runner, python: str, work: Path, wheel: Path) -> tuple[Path, dict]:
    venv = work / "kernelenv"
    vpy = fresh_venv(runner, python, venv, wheel)
    out = work / "kernels"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    env = {"SPIEL_EDGE_KERNELS_OUT": runner.inside(out)}
    t0 = time.perf_counter()
    done = runner.run(
        [vpy, "-m", "spiel_edge.cli", "warmup", "--json"],
        env=env,
        check=True,
        capture_output=True,
        text=True,
    )
    report = json.loads(done.stdout.strip().splitlines()[-1])
    code = "import json, spiel_edge._shipped as s; print(json.dumps(s.identity()))"
    ident = json.loads(
        runner.run([vpy, "-c", code], capture_output=True, text=True, check=True).stdout
    )
    tag = runner.run(
        [
            vpy,
            "-c",
            "import importlib.metadata as m; print(m.distribution('numba').read_text('WHEEL'))",
        ],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    ident["platform"] = platform_tag(tag)
    ident["compile_seconds"] = round(time.perf_counter() - t0, 1)
    ident["kernels"] = report["kernels"]
    ident["peak_rss_mib"] = report.get("peak_rss_mib")
    return out, ident


def verify(runner: Runner, python: str, work: Path, wheel: Path, user: str = "65534") -> dict:
    """The wheel in a fresh venv, read-only, as ``user`` (nobody; "root": an interpreter
    nobody cannot run, e.g. under /root/.pyenv), empty cache, compiling forbidden."""
    venv = work / "verifyenv"
    if runner.root is not None:  # the wheel was written outside the root: install a copy
        shutil.copy(wheel, work / wheel.name)
        wheel = work / wheel.name
    vpy = fresh_venv(runner, python, venv, wheel)
    site = runner.run(
        [vpy, "-c", "import spiel_edge, os; print(os.path.dirname(spiel_edge.__file__))"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    host_site = (runner.root / site.lstrip("/")) if runner.root else Path(site)
    for p in [host_site.parent, *host_site.parent.rglob("*")]:  # site-packages: root's, read-only
        if not p.is_symlink():
            p.chmod(p.stat().st_mode & ~0o222)
    cache = work / "verifycache"
    shutil.rmtree(cache, ignore_errors=True)
    cache.mkdir()
    if user != "root":
        os.chown(cache, int(user), int(user))
    out = work / "verify.ndjson"
    out.unlink(missing_ok=True)
    os.chmod(work, 0o777)
    spiel = runner.inside(venv / "bin/spiel-edge")
    env = {
        "NUMBA_CACHE_DIR": runner.inside(cache),
        "SPIEL_EDGE_NO_COMPILE": "1",
        "HOME": "/nonexistent",
    }
    cmd = [spiel, "run", "--port", SIM, "--frames", str(FRAMES), "--rate", "0"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        _argv(runner, cmd, env, user), stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    first = None
    lines = []
    for line in proc.stdout:
        if first is None:
            first = time.perf_counter() - t0
        lines.append(line)
    err = proc.stderr.read().decode(errors="replace")
    code = proc.wait()
    out.write_bytes(b"".join(lines))
    written = [p for p in cache.rglob("*") if p.is_file()]  # kernels, numba's runtime
    return {
        "exit": code,
        "first_record_s": round(first, 2) if first is not None else None,
        "records": len(lines),
        "compiled_to_cache": len(written),
        "stderr_tail": err.strip().splitlines()[-3:],
        "ndjson": str(out),
    }


def _argv(runner: Runner, cmd: list[str], env: dict, user: str) -> list[str]:
    env = {"PATH": "/usr/bin:/bin", **env}
    prefix = (
        []
        if user == "root"
        else ["setpriv", "--reuid", user, "--regid", user, "--clear-groups", "--"]
    )
    if runner.root is not None:
        return [
            "chroot",
            str(runner.root),
            *prefix,
            "/usr/bin/env",
            "-i",
            *[f"{k}={v}" for k, v in env.items()],
            *cmd,
        ]
    return [*prefix, "/usr/bin/env", "-i", *[f"{k}={v}" for k, v in env.items()], *cmd]


def build(
    runner: Runner, python: str, work: Path, out: Path, check: bool, user: str = "65534"
) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    if runner.root is None:
        step(f"pure wheel with {python}")
        pure = pure_wheel(runner, python, work)
    else:  # a pure wheel is the same everywhere: built by the host, not under emulation
        step("pure wheel with the host's Python, copied into the root")
        built = pure_wheel(Runner(), sys.executable, Path(tempfile.mkdtemp(prefix="spiel-pure-")))
        pure = work / "pure" / built.name
        pure.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(built, pure)
    step("compiling every kernel for a generic CPU in a fresh venv")
    kernels, ident = compile_kernels(runner, python, work, pure)
    wheel = package(pure, kernels, ident, out)
    result = {"wheel": str(wheel), "size_mib": round(wheel.stat().st_size / 2**20, 2), **ident}
    result["kernel_files"] = len(manifest(kernels, ident)["files"])
    result.pop("kernels", None)
    if check:
        step(f"checking {wheel.name}: fresh venv, read-only, nobody, empty cache")
        checked = verify(runner, python, work, wheel, user)
        shutil.copy(checked["ndjson"], str(wheel) + ".sim50.ndjson")
        result["verify"] = checked
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", choices=("host", "aarch64"), default="host")
    ap.add_argument("--python", nargs="+", default=None, help="interpreters (host: paths)")
    ap.add_argument("--out", type=Path, default=REPO / "dist")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--skip-verify", action="store_true")
    ap.add_argument(
        "--verify-user",
        default="65534",
        help="uid the check runs as (default nobody; root for an interpreter under /root)",
    )
    ap.add_argument("--in-root", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    out = args.out.resolve()
    if args.arch == "aarch64" and args.in_root is None:
        work = args.work or Path("/var/tmp/spiel-aarch64")
        inner = [
            sys.executable,
            "-m",
            "tools.release.build_wheels",
            "--arch",
            "aarch64",
            "--out",
            str(out),
            "--in-root",
            "$ARM_ROOT",
        ]
        if args.skip_verify:
            inner.append("--skip-verify")
        env = {
            **os.environ,
            "SPIEL_SMOKE_EXEC": f"cd {shlex.quote(str(REPO))} && "
            + " ".join(a if a == "$ARM_ROOT" else shlex.quote(a) for a in inner),
        }
        script = REPO / "tools/release/aarch64_smoke.sh"
        return subprocess.run(["bash", str(script), str(work)], env=env).returncode
    if args.in_root is not None:
        runner = Runner(args.in_root)
        pythons = args.python or ["/usr/bin/python3"]
        work_of = lambda py: args.in_root / "tmp/spiel-release" / Path(py).name  # noqa: E731
    else:
        runner = Runner()
        pythons = args.python or [
            sys.executable if "venv" not in sys.prefix else "/usr/bin/python3"
        ]
        base = args.work or Path("/var/tmp/spiel-release")
        work_of = lambda py: base / Path(py).name  # noqa: E731
    failed = 0
    for python in pythons:
        result = build(runner, python, work_of(python), out, not args.skip_verify, args.verify_user)
        ok = args.skip_verify or (
            result["verify"]["exit"] == 0 and result["verify"]["compiled_to_cache"] == 0
        )
        failed += not ok
        print(json.dumps({"ok": ok, **result}), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
