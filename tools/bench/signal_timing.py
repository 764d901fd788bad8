"""How fast a signal finalizes `run --record`, with stdout blocked (nobody reads it) and not.

    python -m tools.bench.signal_timing [--rounds 2]

Starts `spiel-edge run --port sim://?scene=model --record R.mcap` per signal (TERM, HUP, INT)
and case, waits until the recording grows (blocked: until it stops growing because stdout is
full), sends the signal and prints, per run, the seconds until the file ends with MCAP's
closing magic (finalized) and until the process is gone, with its exit status.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

MAGIC = b"\x89MCAP0\r\n"


def finalized(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            fh.seek(-len(MAGIC), 2)
            return fh.read() == MAGIC
    except OSError:
        return False


def one(path: Path, sig: signal.Signals, blocked: bool) -> tuple[float, float, int]:
    proc = subprocess.Popen(
        [*[sys.executable, "-m", "spiel_edge.cli"], "run", "--port", "sim://?scene=model"]
        + ["--rate", "0" if blocked else "100", "--record", str(path)],
        stdout=subprocess.PIPE if blocked else subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    last, since = -1, time.monotonic()
    while True:
        size = path.stat().st_size if path.exists() else -1
        if size != last:
            last, since = size, time.monotonic()
        elif size > 20_000 and (not blocked or time.monotonic() - since > 0.5):
            break
        time.sleep(0.05)
    sent = time.monotonic()
    proc.send_signal(sig)
    while not finalized(path) and time.monotonic() - sent < 5:
        time.sleep(0.005)
    done = time.monotonic() - sent
    proc.wait(timeout=30)
    return done, time.monotonic() - sent, proc.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for n in range(args.rounds):
            for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
                for blocked in (True, False):
                    path = Path(tmp) / f"r{n}-{sig.name}-{blocked}.mcap"
                    done, gone, status = one(path, sig, blocked)
                    state = "stdout blocked" if blocked else "stdout read"
                    print(
                        f"{sig.name:8} {state:15} finalized {done:.3f} s, "
                        f"exited {gone:.2f} s, status {status}",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
