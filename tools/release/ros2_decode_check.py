"""Decode every message of a ros2 MCAP recording of a movers run with three third-party
decoders: rosbags, mcap-ros2-support, and Foxglove's own (@foxglove/rosmsg2-serialization,
through node; tools/release/ros2_decode_check.mjs). Reports messages and failures per decoder and
topic as JSON.

    python -m tools.release.ros2_decode_check --frames 1700 -o /tmp/movers.mcap \\
        --node-modules /tmp/npm/node_modules

The recording: `spiel-edge run --port 'sim://?scene=model&movers=3&seed=S' --max-targets 4
--track --record FILE --record-profile ros2 --parent-frame base_link` (point, targets,
tracks, range, /diagnostics, /tf_static, position, acquisition, background). Foxglove's
decoders need node and, in the folder given, `npm install @foxglove/rosmsg
@foxglove/rosmsg2-serialization @mcap/core fzstd`; without them that decoder is reported as
not run.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path


def record(path: Path, frames: int, seed: int) -> None:
    from spiel_edge.cli import main

    args = ["run", "--port", f"sim://?scene=model&movers=3&seed={seed}", "--frames", str(frames)]
    args += ["--rate", "0", "--max-targets", "4", "--track", "-o", os.devnull, "--no-status"]
    args += ["--record", str(path), "--record-profile", "ros2", "--force"]
    args += ["--parent-frame", "base_link", "--translation-m", "0.1,0,0.25"]
    code = main(args)
    if code != 0:
        raise SystemExit(f"the run failed with status {code}")


def with_rosbags(path: Path) -> dict:
    from rosbags.highlevel import AnyReader

    total, failures, topics = 0, Counter(), Counter()
    with AnyReader([path]) as reader:
        for connection, _t, raw in reader.messages():
            total += 1
            topics[connection.topic] += 1
            try:
                message = reader.deserialize(raw, connection.msgtype)
                if reader.typestore.serialize_cdr(message, connection.msgtype) != raw:
                    raise ValueError("re-encodes differently")
            except Exception as exc:  # noqa: BLE001 - every failure is counted
                failures[f"{connection.topic}: {exc}"[:120]] += 1
    return {"messages": total, "failures": sum(failures.values()), "by_topic": dict(topics),
            "first_failures": list(failures)[:5]}  # fmt: skip


def with_mcap_ros2(path: Path) -> dict:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    total, failures = 0, Counter()
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, decoded in reader.iter_decoded_messages():
            total += 1
            if decoded is None:
                failures[channel.topic] += 1
    return {
        "messages": total,
        "failures": sum(failures.values()),
        "first_failures": list(failures)[:5],
    }


def with_foxglove(path: Path, node_modules: str | None) -> dict:
    node = shutil.which("node")
    script = Path(__file__).with_name("ros2_decode_check.mjs")
    if not node or not node_modules or not Path(node_modules, "@foxglove").is_dir():
        return {"not_run": "needs node and --node-modules with Foxglove's packages"}
    done = subprocess.run(
        [node, str(script), str(path)],
        env={**os.environ, "NODE_PATH": str(Path(node_modules).resolve())},
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1:] or ["node failed"]}
    return json.loads(done.stdout)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default="ros2_decode_check.mcap", help="the recording")
    ap.add_argument("--frames", type=int, default=1700, help="acquisitions (about 6 messages each)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--reuse", action="store_true", help="decode an existing recording")
    ap.add_argument("--node-modules", help="folder with Foxglove's npm packages")
    args = ap.parse_args(argv)
    path = Path(args.output)
    if not (args.reuse and path.is_file()):
        record(path, args.frames, args.seed)
    report = {
        "recording": str(path),
        "rosbags": with_rosbags(path),
        "mcap_ros2_support": with_mcap_ros2(path),
        "foxglove": with_foxglove(path, args.node_modules),
    }
    print(json.dumps(report, indent=1))
    failed = sum(r.get("failures", 0) for r in report.values() if isinstance(r, dict))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
