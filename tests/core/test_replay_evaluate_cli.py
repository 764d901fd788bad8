import json

import numpy as np
import pytest

from spiel_edge.cli import main
from spiel_edge.measure.evaluate import split_by_position
from tests.core.spiel_csv_fixture import write_spiel_csv


@pytest.fixture(scope="module")
def folders(subset, tmp_path_factory):
    return write_spiel_csv(subset, tmp_path_factory.mktemp("rec"))


def read_records(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_replay_writes_one_record_per_acquisition(folders, tmp_path, subset):
    frames_dir, bg_dir = folders
    out = tmp_path / "out.ndjson"
    assert (
        main(
            [
                "replay",
                str(frames_dir),
                "--background",
                str(bg_dir),
                "--association",
                "geometric",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    records = read_records(out)
    assert [r["source"] for r in records] == sorted(subset.names)
    fixed = [r for r in records if r["position_mm"] is not None]
    assert len(fixed) / len(records) > 0.95
    for r in records:
        assert set(r) >= {"source", "position_mm", "reason", "residual_mm", "echoes", "matched"}
        assert len(r["echoes"]) == len(r["matched"]) == 4
        for echoes, m in zip(r["echoes"], r["matched"], strict=True):
            assert echoes == sorted(echoes)
            assert m is None or 0 <= m < len(echoes)
        assert (r["position_mm"] is None) == (r["reason"] is not None)
    # the positions are right: median error on the vendored frames below 25 mm, z within 15 mm
    truth = dict(zip(subset.names, subset.truth_mm, strict=True))
    errors = [
        np.linalg.norm(np.array(r["position_mm"]) - truth[r["source"]])
        for r in fixed
        if truth[r["source"]][2] != 90
    ]
    assert np.median(errors) < 25


def test_replay_survives_bad_files(folders, tmp_path, subset):
    frames_dir, bg_dir = folders
    bad = tmp_path / "bad"
    bad_bg = tmp_path / "bad_bg"
    bad.mkdir()
    bad_bg.mkdir()
    good = subset.names[0]
    (bad / good).write_text((frames_dir / good).read_text())
    (bad_bg / good).write_text((bg_dir / good).read_text())
    cases = {
        "a_malformed_frames.csv": "1 2 x\n3 4 5\n",
        "b_ragged_frames.csv": "1 2 3\n4 5\n",
        "c_nan_frames.csv": "\n".join(" ".join(["nan"] * 64) for _ in range(4)),
        "d_three_channels_frames.csv": "\n".join(" ".join(["1"] * 64) for _ in range(3)),
        "e_short_frames.csv": "\n".join(" ".join(["1"] * 32) for _ in range(4)),
        "f_nobackground_frames.csv": (frames_dir / good).read_text(),
        "g_flat_frames.csv": "\n".join(" ".join(["0"] * 64) for _ in range(4)),
        "h_saturated_frames.csv": "\n".join(" ".join(["65535"] * 64) for _ in range(4)),
        "i_empty_frames.csv": "",
    }
    for name, text in cases.items():
        (bad / name).write_text(text)
        if name != "f_nobackground_frames.csv":
            (bad_bg / name).write_text(
                text if "flat" in name or "saturated" in name else (bg_dir / good).read_text()
            )
    out = tmp_path / "out.ndjson"
    status = main(
        [
            "replay",
            str(bad),
            "--background",
            str(bad_bg),
            "--association",
            "geometric",
            "-o",
            str(out),
        ]
    )
    assert status == 1
    records = {r["source"]: r for r in read_records(out)}
    assert len(records) == len(cases) + 1
    assert records[good]["position_mm"] is not None
    for name in (
        "a_malformed",
        "b_ragged",
        "c_nan",
        "d_three_channels",
        "e_short",
        "f_nobackground",
        "i_empty",
    ):
        r = records[f"{name}_frames.csv"]
        assert r["position_mm"] is None and r["error"] and f"{name}_frames.csv" in r["error"]
    for name, reason in (("g_flat", "flat"), ("h_saturated", "saturated")):
        r = records[f"{name}_frames.csv"]
        assert r["position_mm"] is None and reason in r["reason"] and "error" not in r


def test_replay_missing_folder_is_a_clean_error(tmp_path, capsys):
    assert main(["replay", str(tmp_path), "--format", "spiel-csv"]) == 2
    assert "no *_frames.csv" in capsys.readouterr().err


def test_evaluate_reports_metrics_on_the_vendored_frames(folders, capsys):
    frames_dir, bg_dir = folders
    assert (
        main(
            [
                "evaluate",
                str(frames_dir),
                "--background",
                str(bg_dir),
                "--association",
                "geometric",
                "--exclude-z",
                "90",
                "--json",
            ]
        )
        == 0
    )
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["fix_rate"] == 1.0
    assert summary["fix_rate_seen3"] == 1.0
    assert summary["mean_mm"] < 30 and summary["median_mm"] < 22
    assert summary["association_accuracy"] > 0.93
    assert set(summary["by_height"]) == {"100", "180", "220"}


def test_split_by_position_is_deterministic_and_disjoint(subset):
    train, val = split_by_position(subset.names)
    assert train.isdisjoint(val) and len(val) >= 3 and len(train) > len(val)
    assert split_by_position(reversed(subset.names)) == (train, val)
