"""Smoke tests of tools/release/fuzz_protocol.py and tools/bench/bench_protocol.py (not timed)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType

import pytest

TOOLS = Path(__file__).resolve().parents[2] / "tools"


def load(path: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(Path(path).name, TOOLS / f"{path}.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_fuzz_random_loop(capsys: pytest.CaptureFixture[str]) -> None:
    fuzz = load("release/fuzz_protocol")
    assert fuzz.main(["--iterations", "3000", "--seed", "5"]) == 0
    assert json.loads(capsys.readouterr().out)["failures"] == 0
    fuzz.one_input(b"")
    fuzz.one_input(b"\x00" * 10)


def test_bench_prints_json(capsys: pytest.CaptureFixture[str]) -> None:
    result = load("bench/bench_protocol").main(["--frames", "128", "--repeat", "1"])
    printed = json.loads(capsys.readouterr().out)
    assert printed == result and result["decode_MBps"] > 0 and result["wire_bytes"] > 128 * 4096
