"""Peak memory and time of every command on the hostile inputs of issue 28 (docs/reliability.md).

    python -m tools.bench.hostile_memory [--json]

Builds each hostile input in a temporary folder (sparse files and small zips: a few MB on
disk), runs the command in a fresh process that reports its own high-water mark (VmHWM) at
exit, and prints per case the exit status, the peak resident memory in MiB and the seconds
it took. The target: every peak at most 300 MiB, every status documented (0, 1, 2, 130).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

LIMIT_MIB = 300
PEAK_SNIPPET = """
import atexit, sys
def _peak():
    with open("/proc/self/status") as status:
        sys.stderr.write(next(line for line in status if line.startswith("VmHWM:")))
atexit.register(_peak)
from spiel_edge.cli import main
sys.exit(main(sys.argv[1:]))
"""
GIB = 1 << 30


def _npy_header(descr: str, shape: tuple) -> bytes:
    text = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}"
    total = 10 + len(text) + 1
    body = (text + " " * ((-total) % 64) + "\n").encode("latin1")
    return b"\x93NUMPY\x01\x00" + len(body).to_bytes(2, "little") + body


def _sparse(path: Path, head: bytes, size: int) -> Path:
    with open(path, "wb") as fh:
        fh.write(head)
        fh.truncate(size)
    return path


def _bomb(path: Path, mib: int) -> Path:
    with (
        zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf,
        zf.open("median.npy", "w", force_zip64=True) as member,
    ):
        member.write(_npy_header("<f8", (mib * 131072,)))
        zero = bytes(1 << 20)
        for _ in range(mib):
            member.write(zero)
    return path


def cases(d: Path) -> dict[str, list[str]]:
    """name -> command line (after `spiel-edge`)."""
    from spiel_edge.profile.schema import dump_toml, load_profile, profile_to_dict

    sim = "sim://?scene=model"
    big_npy = _sparse(d / "bg.npy", _npy_header("<f8", (4, 80_000_000)), int(2.5 * GIB))
    np.save(d / "str.npy", np.array(["a", "b"]))
    os.mkfifo(d / "out.fifo")
    data = profile_to_dict(load_profile("spiel-icra23"))
    data["scene"]["static_model"] = str(_bomb(d / "model.npz", 80))
    (d / "bomb_profile.toml").write_text(dump_toml(data))
    _bomb(d / "scenes.npz", 300)
    _sparse(d / "pos.csv", b"0,0,150\n", 2 * GIB)
    (d / "cfg").mkdir()
    _sparse(d / "cfg" / "spiel-edge.env", b"SPIEL_PORT=sim://\n", 2 * GIB)
    (d / "csv").mkdir()
    _sparse(d / "csv" / "a_frames.csv", b"1 2 3\n", 500 << 20)
    with open(d / "garbage.mcap", "wb") as fh:
        fh.write(os.urandom(64 << 20))
    (d / "deep.toml").write_text("a = " + "[" * 5000 + "]" * 5000)
    (d / "nan.toml").write_text("[associate]\nmissing_penalty_mm = nan\n")
    (d / "cal.toml").write_text("[geometry]\n")
    os.link(d / "cal.toml", d / "cal_link.ndjson")
    return {
        "background .npy, sparse 2.5 GB": ["run", "--port", sim, "--background", str(big_npy)],
        "background .npy of strings": ["run", "--port", sim, "--background", str(d / "str.npy")],
        "output a FIFO nobody reads": ["run", "--port", sim, "-o", str(d / "out.fifo")],
        "static model, 80 MiB zip bomb": ["run", "--port", sim, "--profile", str(d / "bomb_profile.toml")],
        "evaluate, 300 MiB zip bomb": ["evaluate", str(d / "scenes.npz")],
        "calibrate --positions, sparse 2 GB": ["calibrate", "--positions", str(d / "pos.csv"), "--port", sim],
        "doctor, spiel-edge.env sparse 2 GB": ["doctor", "--config", str(d / "cfg"), "--skip-numba"],
        "replay, frames file sparse 500 MB": ["replay", str(d / "csv"), "-o", os.devnull],
        "replay, 64 MB of random bytes as MCAP": ["replay", str(d / "garbage.mcap"), "--format", "mcap", "-o", os.devnull],
        "profile nested 5000 deep": ["replay", str(d / "csv"), "--profile", str(d / "deep.toml")],
        "calibration with NaN": ["replay", str(d / "csv"), "--calibration", str(d / "nan.toml")],
        "output a hard link of the calibration": ["run", "--port", sim, "--calibration", str(d / "cal.toml"), "-o", str(d / "cal_link.ndjson"), "--force"],
        "board: counter restarts": ["run", "--port", "sim://?lie=counter-restart", "-o", os.devnull],
        "board: stream never completes": ["run", "--port", "sim://?lie=incomplete", "-o", os.devnull],
        "board: stream says 3 of 4 channels (background)": ["background", "--port", "sim://?lie=fewer-channels", "-o", str(d / "bg_out.npy")],
        "board: endless config (config pull)": ["config", "pull", "--port", "sim://?lie=endless-config", str(d / "board.toml")],
        "board: endless config (run)": ["run", "--port", "sim://?lie=endless-config", "-o", os.devnull],
    }  # fmt: skip


def measure(args: list[str], timeout_s: float = 300.0) -> dict:
    t0 = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-c", PEAK_SNIPPET, *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )
    seconds = time.monotonic() - t0
    peak = re.search(r"VmHWM:\s+(\d+) kB", proc.stderr)
    lines = [line for line in proc.stderr.splitlines() if not line.startswith("VmHWM")]
    return {
        "status": proc.returncode,
        "peak_mib": round(int(peak.group(1)) / 1024, 1) if peak else None,
        "seconds": round(seconds, 2),
        "message": (lines[-1] if lines else "")[:160],
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true")
    opts = parser.parse_args()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, args in cases(Path(tmp)).items():
            results[name] = measure(args)
            if not opts.json:
                r = results[name]
                print(
                    f"{r['peak_mib']:>7} MiB {r['seconds']:>6.2f} s  status {r['status']}  {name}"
                )
                print(f"{'':26}{r['message']}")
    worst = max(r["peak_mib"] or 0 for r in results.values())
    ok = worst <= LIMIT_MIB and all(r["status"] in (0, 1, 2, 130) for r in results.values())
    if opts.json:
        print(json.dumps({"worst_peak_mib": worst, "ok": ok, "cases": results}, indent=1))
    else:
        print(f"worst peak {worst} MiB (target <= {LIMIT_MIB}): {'met' if ok else 'NOT met'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
