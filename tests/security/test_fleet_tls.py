"""docs/security.md's fleet set-up, run on loopback: Zenoh mutual TLS with certificates this
test makes (openssl), access control by certificate name. Board `front`'s records are fused;
board `back`'s computer (a valid certificate) cannot publish as `front`; a peer without a
client certificate cannot connect at all."""

from __future__ import annotations

import json
import re
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh", reason="the 'zenoh' extra is not installed")
OPENSSL = shutil.which("openssl")
pytestmark = pytest.mark.skipif(OPENSSL is None, reason="the openssl command is not installed")

DOC = Path(__file__).resolve().parents[2] / "docs" / "security.md"


def _block_after(label: str) -> str:
    """The fenced block that follows the first line naming ``label`` in docs/security.md."""
    text = DOC.read_text()
    start = text.index(f"`{label}`:")
    m = re.compile(r"```json5\n(.*?)```", re.S).search(text, start)
    assert m is not None, label
    return m[1]


def _certs(d: Path) -> None:
    def run(*args):
        subprocess.run([OPENSSL, *args], check=True, capture_output=True, cwd=d, timeout=60)

    run(
        "req",
        "-x509",
        "-newkey",
        "ec",
        "-pkeyopt",
        "ec_paramgen_curve:P-256",
        "-nodes",
        "-days",
        "2",
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
        "-subj",
        "/CN=test-ca",
    )
    for name in ("fuse", "front", "back"):
        run(
            "req",
            "-newkey",
            "ec",
            "-pkeyopt",
            "ec_paramgen_curve:P-256",
            "-nodes",
            "-keyout",
            f"{name}.key",
            "-out",
            f"{name}.csr",
            "-subj",
            f"/CN={name}",
        )
        (d / f"{name}.ext").write_text(
            f"subjectAltName=DNS:{name}.local,DNS:localhost,IP:127.0.0.1\n"
            "extendedKeyUsage=serverAuth,clientAuth\n"
        )
        run(
            "x509",
            "-req",
            "-in",
            f"{name}.csr",
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-days",
            "2",
            "-out",
            f"{name}.pem",
            "-extfile",
            f"{name}.ext",
        )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _config(d: Path, label: str, port: int, as_board: str | None = None) -> Path:
    text = _block_after(label).replace("/etc/spiel-edge/tls/", f"{d}/")
    text = text.replace("tls/0.0.0.0:7447", f"tls/127.0.0.1:{port}")  # loopback only here
    text = text.replace("tls/fuse.local:7447", f"tls/127.0.0.1:{port}")
    if as_board:
        text = text.replace("/front.", f"/{as_board}.")
    path = d / (f"{as_board}.json5" if as_board else label)
    path.write_text(text)
    return path


def _record(k: int, x_mm: float) -> dict:
    return {
        "acquisition": k,
        "device_time_us": int((10.0 + 0.025 * k) * 1e6),
        "host_time": time.time(),
        "targets": [
            {
                "position_mm": [x_mm, 0.0, 200.0],
                "covariance_mm2": (np.eye(3) * 16).tolist(),
                "score": 1.0,
            }
        ],
    }


class Collect:
    def __init__(self):
        self.records = []

    def write(self, record):
        self.records.append(json.loads(json.dumps(record)))


def test_the_documented_fleet_set_up_fuses_only_each_boards_own_records(tmp_path, monkeypatch):
    from spiel_edge.outputs.ros2 import ZenohSettings
    from spiel_edge.outputs.zenoh import ZenohSink, session_config
    from spiel_edge.robot.description import robot_from_dict
    from spiel_edge.robot.zenoh_fuse import ZenohFuse, zenoh_config

    monkeypatch.delenv("ZENOH_CONFIG", raising=False)
    _certs(tmp_path)
    port = _free_port()
    fuse_cfg = _config(tmp_path, "fuse.json5", port)
    robot = robot_from_dict(
        {
            "robot": {"name": "rover"},
            "trigger": {"period_ms": 25.0, "max_range_m": 0.8},
            "board": [
                {"name": "front", "key": "robot/front"},
                {"name": "back", "key": "robot/back", "rotation_rpy_deg": [0, 90, 180]},
            ],
        }
    )
    sink = Collect()
    fuse = ZenohFuse(robot, sink, config=zenoh_config(config=str(fuse_cfg)))
    stop = threading.Event()
    worker = threading.Thread(target=fuse.run, args=(stop,), kwargs={"idle_s": 1.5})
    worker.start()
    front = ZenohSink(
        "robot/front",
        settings=ZenohSettings(config_file=str(_config(tmp_path, "front.json5", port))),
    )
    back_cfg = _config(tmp_path, "front.json5", port, as_board="back")
    back = zenoh.open(session_config(str(back_cfg)))  # a valid certificate, CN=back
    no_cert = json.loads(
        json.dumps(
            {
                "mode": "peer",
                "connect": {"endpoints": [f"tls/127.0.0.1:{port}"]},
                "listen": {"endpoints": []},
                "scouting": {"multicast": {"enabled": False}},
                "transport": {"link": {"tls": {"root_ca_certificate": str(tmp_path / "ca.pem")}}},
            }
        )
    )
    stranger = zenoh.open(zenoh.Config.from_json5(json.dumps(no_cert)))
    try:
        time.sleep(1.5)  # TLS handshakes
        assert list(back.info.peers_zid()) and not list(stranger.info.peers_zid())
        forger, outsider = (
            back.declare_publisher("robot/front"),
            stranger.declare_publisher("robot/front"),
        )
        for k in range(40):
            front.write(_record(k, 0.0))
            forger.put(json.dumps(_record(k, 900.0)))  # back's computer, posing as front
            outsider.put(json.dumps(_record(k, -900.0)))  # no client certificate
            time.sleep(0.025)
    finally:
        worker.join(timeout=20)
        stop.set()
        for s in (back, stranger):
            s.close()
        front.close()
        fuse.close()
    xs = [t["position_mm"] for r in sink.records for t in r["targets"]]
    assert len(sink.records) >= 30 and xs
    # front sees its target at (0, 0, 200) mm in its frame (no rotation); forged ones are 900 off
    assert all(abs(p[0]) < 100 for p in xs), [p for p in xs if abs(p[0]) >= 100][:3]
    assert fuse.fuser.stats["front"]["reports"] >= 30
    assert fuse.fuser.stats["front"]["reports"] <= 40  # nothing but its own
