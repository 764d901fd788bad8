from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

BOARD = """
[[board]]
name = "{name}"
port = "{port}"
translation_m = {translation}
{rotation}
{slot}
"""


def robot_text(boards: list[dict], trigger: str = "period_ms = 25.0\nmax_range_m = 0.8") -> str:
    text = '[robot]\nname = "test"\n\n[trigger]\n' + trigger + "\n"
    for b in boards:
        text += BOARD.format(
            name=b["name"],
            port=b.get("port", f"sim://{b['name']}"),
            translation=b.get("translation", "[0.1, 0.0, 0.0]"),
            rotation=b.get("rotation", "rotation_rpy_deg = [0.0, 90.0, 0.0]"),
            slot=b.get("slot", ""),
        )
    return textwrap.dedent(text)


@pytest.fixture
def write_robot(tmp_path):
    def write(boards: list[dict], **kw) -> Path:
        path = tmp_path / "robot.toml"
        path.write_text(robot_text(boards, **kw))
        return path

    return write


@pytest.fixture
def zenoh_output_settings(monkeypatch) -> list:
    """The ZenohSettings each --zenoh output is opened with (no session is opened)."""
    from spiel_edge.outputs import fanout
    from spiel_edge.outputs.sink import Sink as Contract

    seen: list = []

    class Sink(Contract):  # the contract's defaults (no view line: `run --robot` asks)
        def write(self, record):
            pass

        def close(self):
            pass

    monkeypatch.setattr(fanout, "_zenoh_sink", lambda *a: seen.append(a[3]) or Sink())
    return seen
