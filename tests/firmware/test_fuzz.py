"""A short libFuzzer run of the device's request decoder (tools/release/firmware_fuzz.py): the harness
builds with clang -fsanitize=fuzzer,address,undefined, counts its own inputs and ends without
a crash or a sanitizer report. The long run (10 million inputs) is in docs/firmware.md.
Skipped where clang or its fuzzer runtime is missing (Debian: clang, libclang-rt-14-dev)."""

from __future__ import annotations

import json
import shutil

import pytest

from tools.release import firmware_fuzz

RUNS = 5000


def test_a_short_fuzz_run_is_clean(tmp_path, capsys):
    if shutil.which("clang") is None:
        pytest.skip("clang not found (Debian: apt-get install clang libclang-rt-14-dev)")
    status = firmware_fuzz.main(["--runs", str(RUNS), "--json", "--out", str(tmp_path)])
    captured = capsys.readouterr()
    if status == 2:
        pytest.skip(captured.err.strip())
    result = json.loads(captured.out)
    assert status == 0 and not result["crashed"], result
    assert result["harness_inputs"] == result["libfuzzer_units"] == RUNS
    assert result["seeds"] > 10 and result["corpus_files"] >= result["seeds"]


def test_the_tool_refuses_a_bad_bound(capsys):
    assert firmware_fuzz.main(["--runs", "0"]) == 2
    assert "must be positive" in capsys.readouterr().err
