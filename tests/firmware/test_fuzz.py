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
    # libFuzzer counts RUNS units; the harness may count a few more: libFuzzer runs an input
    # again, uncounted, when its mallocs and frees differ (its leak check), as on CI once (+16).
    assert result["libfuzzer_units"] == RUNS
    assert RUNS <= result["harness_inputs"] <= RUNS * 1.05, result
    assert result["seeds"] > 10 and result["corpus_files"] >= result["seeds"]


def test_the_tool_refuses_a_bad_bound(capsys):
    assert firmware_fuzz.main(["--runs", "0"]) == 2
    assert "must be positive" in capsys.readouterr().err


def _harness_types() -> list[int]:
    """fuzz_request.c's types[] table, its SP_MSG_ names resolved through spiel_registry.h."""
    import re

    root = firmware_fuzz.FIRMWARE
    registry = (root.parent / "c" / "spiel_registry.h").read_text()
    names = dict(re.findall(r"#define (SP_MSG_\w+)\s+(0x[0-9A-Fa-f]+)u", registry))
    source = (root / "fuzz" / "fuzz_request.c").read_text()
    table = re.search(r"static const uint16_t types\[\] = \{(.*?)\};", source, re.S).group(1)
    out = []
    for token in (t.strip() for t in table.split(",")):
        if token:
            out.append(int(names.get(token, token.rstrip("u")), 16))
    return out


def test_the_seed_records_use_the_harness_type_table():
    assert list(firmware_fuzz.FRAMED_TYPES) == _harness_types()


def test_the_update_seeds_are_whole_updates():
    seeds = firmware_fuzz.update_seeds()
    assert len(seeds) == 6
    for name, data in seeds.items():
        assert data[0] & firmware_fuzz.FRAMED
        body, kinds = data[4:], []
        while len(body) >= 5:
            n = int.from_bytes(body[3:5], "little")
            kinds.append(firmware_fuzz.FRAMED_TYPES[body[0]])
            body = body[5 + n :]
        assert body == b""
        test = kinds.index(firmware_fuzz.FW_TEST)
        assert kinds[:3] == [firmware_fuzz.HELLO, firmware_fuzz.FW_INFO, firmware_fuzz.FW_BEGIN]
        assert firmware_fuzz.FW_VERIFY in kinds[:test] and firmware_fuzz.FW_WRITE in kinds
        after = firmware_fuzz.REBOOT if "rollback" in name else firmware_fuzz.FW_CONFIRM
        assert after in kinds[test:]


def test_the_harness_runs_a_whole_update_and_its_rollback(tmp_path):
    """The seeds reach every FW_* request, the reset into the trial image, FW_CONFIRM and the
    rollback (the harness built with SPIEL_FUZZ_TRACE prints each answer and boot)."""
    import subprocess

    if shutil.which("clang") is None:
        pytest.skip("clang not found (Debian: apt-get install clang libclang-rt-14-dev)")
    done = subprocess.run(
        ["make", "-s", "TARGET=fuzz", f"BUILD={tmp_path}", "CFLAGS_EXTRA=-DSPIEL_FUZZ_TRACE=1"],
        cwd=firmware_fuzz.FIRMWARE,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if done.returncode != 0 and "fuzzer" in done.stderr:
        pytest.skip(done.stderr.strip().splitlines()[-1])
    assert done.returncode == 0, done.stderr
    for name, data in firmware_fuzz.update_seeds().items():
        (tmp_path / name).write_bytes(data)
        run = subprocess.run(
            [str(tmp_path / "spiel_fuzz"), str(tmp_path / name)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert run.returncode == 0, run.stderr
        lines = [x for x in run.stderr.splitlines() if x.startswith("spiel_fuzz: ")]
        for msg_type in (0x0041, 0x0042, 0x0043, 0x0044):
            assert any(f"0x{msg_type:04x} seq" in x and ": ok" in x for x in lines), lines
        assert "spiel_fuzz: boot (reset 1): slot 1" in lines
        if "rollback" not in name:
            assert any("0x0045 seq" in x and ": ok" in x for x in lines), lines
        else:  # the reset before FW_CONFIRM rolls back to slot 0 (or, from the recovery loader,
            # keeps slot 1: slot 0 holds no image)
            want = 0 if name.endswith("-9") else 1
            assert f"spiel_fuzz: boot (reset 2): slot {want}" in lines, lines
