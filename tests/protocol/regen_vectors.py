"""Rewrite firmware_protocol/test_vectors.json from the implementation.

Run only when the wire format changes on purpose:
    .venv/bin/python -m tests.protocol.regen_vectors
"""

import json
from pathlib import Path

from spiel_edge.protocol.vectors import build_test_vectors

PATH = Path(__file__).resolve().parents[2] / "firmware_protocol" / "test_vectors.json"


def render() -> str:
    return json.dumps(build_test_vectors(), indent=1) + "\n"


if __name__ == "__main__":
    PATH.write_text(render())
    print(f"wrote {PATH}")
