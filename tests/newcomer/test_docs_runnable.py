"""Every docs block marked ``<!-- runnable -->`` runs as written on a fresh clone: no hardware,
no ../shared. Paths into the repository (spiel_edge/data/...) are written from its root; the
test runs in a scratch folder and points them there. A line ending in ``&`` is a server (the
virtual board on a pty): started, waited for (its --link), stopped at the end."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MARK = "<!-- runnable -->"


def blocks() -> list[tuple[str, list[str]]]:
    found = []
    for page in sorted((ROOT / "docs").glob("*.md")):
        text = page.read_text()
        for n, m in enumerate(re.finditer(re.escape(MARK) + r"\n```sh\n(.*?)```", text, re.S)):
            lines = [ln for ln in m.group(1).splitlines() if ln.strip() and not ln.startswith("#")]
            found.append((f"{page.name}#{n + 1}", lines))
    return found


def test_there_are_runnable_blocks():
    names = {name.split("#")[0] for name, _ in blocks()}
    assert {"pictures.md", "virtual-board.md", "pipeline.md", "tracking.md", "robot.md"} <= names
    assert "integrator.md" in names


@pytest.mark.parametrize("name, lines", blocks(), ids=[b[0] for b in blocks()])
def test_docs_block_runs(name, lines, tmp_path):
    if name.startswith("pictures.md"):
        pytest.importorskip("matplotlib", reason="the pictures need the 'plot' extra")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    env.pop("SPIEL_PORT", None)
    servers = []
    try:
        for line in lines:
            line = line.replace("spiel_edge/data/", f"{ROOT}/spiel_edge/data/")
            line = line.replace("/tmp/spiel-sim", str(tmp_path / "spiel-sim"))
            command = line.split("  #")[0].strip()
            if command.endswith("&"):
                args = shlex.split(command[:-1])
                servers.append(
                    subprocess.Popen(
                        args, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
                    )
                )
                link = Path(args[args.index("--link") + 1]) if "--link" in args else None
                deadline = time.monotonic() + 60
                while link is not None and not link.exists() and time.monotonic() < deadline:
                    time.sleep(0.05)
                continue
            done = subprocess.run(
                ["bash", "-c", command], cwd=tmp_path, env=env, capture_output=True, text=True,
                timeout=240,
            )  # fmt: skip
            assert done.returncode == 0, f"{name}: {command}\n{done.stderr[-2000:]}"
    finally:
        for server in servers:
            server.terminate()
            server.communicate(timeout=10)
