"""Every command runs on what ships: evaluate, calibrate and replay on the vendored subset, and
every recording input is told by its content (one line otherwise)."""

from __future__ import annotations

import json
import zipfile
from importlib import resources

import numpy as np
import pytest

from spiel_edge.cli import main
from spiel_edge.errors import InputError
from spiel_edge.recordings.kinds import recording_kind
from spiel_edge.recordings.labelled import load_labelled

SUBSET = str(resources.files("spiel_edge") / "data" / "spiel_icra23_subset.npz")


def test_the_subset_is_a_labelled_set():
    assert recording_kind(SUBSET) == "labelled"
    data = load_labelled(SUBSET, exclude_z=(90.0,))
    assert data.frames.shape[1:] == (4, 64) and data.truth_mm.shape == (len(data), 3)
    assert 90.0 not in set(data.truth_mm[:, 2])


def test_evaluate_on_the_subset(capsys):
    assert main(["evaluate", SUBSET, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == 150  # z = 100 and 180 mm, z = 90 left out
    assert set(out["by_height"]) == {"100", "180", "220"}
    assert 5.0 < out["mean_mm"] < 30.0


def test_evaluate_explains_its_columns(capsys):
    assert main(["evaluate", SUBSET, "--split", "val"]) == 0
    out = capsys.readouterr().out
    assert "recall: true targets found within 30 mm" in out and "cov1:" in out


def test_replay_keeps_truth_and_prints_a_summary(tmp_path, capsys):
    out = tmp_path / "r.ndjson"
    assert main(["replay", SUBSET, "-o", str(out)]) == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 228
    first = records[0]
    assert first["source"].endswith("_frames.csv") and len(first["truth_mm"]) == 3
    err = capsys.readouterr().err
    assert "replayed 228 acquisitions" in err and "against truth_mm: mean" in err


def test_replay_to_mcap_and_back_keeps_truth(tmp_path, capsys):
    rec = tmp_path / "r.mcap"
    assert main(["replay", SUBSET, "-o", str(rec)]) == 0
    again = tmp_path / "again.ndjson"
    assert main(["replay", str(rec), "-o", str(again)]) == 0
    records = [json.loads(line) for line in again.read_text().splitlines()]
    assert len(records) == 228 and all(len(r["truth_mm"]) == 3 for r in records)
    assert "against truth_mm" in capsys.readouterr().err


def test_calibrate_reads_the_subset(tmp_path, capsys):
    out = tmp_path / "cal.toml"
    rc = main(
        [
            "calibrate",
            "--recordings",
            SUBSET,
            "--fix",
            "receivers",
            "--fix",
            "emitter",
            "--force",
            "-o",
            str(out),
        ]
    )
    assert rc == 0 and out.is_file()
    assert "225 acquisitions" in capsys.readouterr().err


def _written(path, data):
    path.write_bytes(data)
    return path


def _npy(path):
    np.save(path.with_suffix(".npy"), np.zeros(3))
    return path.with_suffix(".npy")


def _empty_zip(path):
    zipfile.ZipFile(path, "w").close()
    return path


def _other_npz(path):
    np.savez(path, median=np.zeros(3), mad=np.ones(3))
    return path


@pytest.mark.parametrize(
    "make, says",
    [
        (lambda p: _written(p, b"hello\n"), "not a recording"),
        (lambda p: _written(p, b""), "an empty file"),
        (_npy, ".npy"),
        (_other_npz, "without frames"),
        (_empty_zip, "without frames"),
    ],
)
@pytest.mark.parametrize("command", ["evaluate", "replay", "calibrate"])
def test_what_is_not_a_recording_is_one_line(tmp_path, capsys, make, says, command):
    path = make(tmp_path / "x.npz")
    args = {
        "evaluate": ["evaluate", str(path)],
        "replay": ["replay", str(path)],
        "calibrate": ["calibrate", "--recordings", str(path)],
    }[command]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0] and "internal error" not in err[0], err


def test_evaluate_refuses_an_mcap_by_content(tmp_path, capsys):
    rec = tmp_path / "r.bin"  # no .mcap suffix: the content says what it is
    rec.write_bytes(b"\x89MCAP0\r\n" + b"\0" * 32)
    assert main(["evaluate", str(rec)]) == 2
    err = capsys.readouterr().err
    assert "an MCAP recording; expected" in err


def test_a_labelled_set_with_bad_shapes_is_refused(tmp_path):
    path = tmp_path / "bad.npz"
    np.savez(
        path,
        frames=np.zeros((2, 4, 64)),
        backgrounds=np.zeros((2, 4, 64)),
        truth_mm=np.zeros((3, 3)),
        names=np.array(["a", "b"]),
    )
    with pytest.raises(InputError, match="truth_mm"):
        load_labelled(path)


def test_a_virtual_board_recording_replays_with_its_truth(tmp_path, capsys):
    rec = tmp_path / "run.mcap"
    out = tmp_path / "run.ndjson"
    assert (
        main(["run", "--port", "sim://", "--frames", "6", "-o", str(out), "--record", str(rec)])
        == 0
    )
    again = tmp_path / "again.ndjson"
    assert main(["replay", str(rec), "-o", str(again)]) == 0
    live = [json.loads(line) for line in out.read_text().splitlines()]
    replayed = [json.loads(line) for line in again.read_text().splitlines()]
    assert [r["truth_mm"] for r in replayed] == [r["truth_mm"] for r in live]
    assert "against truth_mm" in capsys.readouterr().err


def test_a_background_is_told_by_its_content(tmp_path, capsys):
    from spiel_edge.data import load_subset

    npy = tmp_path / "bg.data"  # a .npy under another name
    np.save(tmp_path / "bg.npy", load_subset().backgrounds[0])
    npy.write_bytes((tmp_path / "bg.npy").read_bytes())
    out = tmp_path / "r.ndjson"
    assert (
        main(["run", "--port", "sim://", "--frames", "2", "--background", str(npy), "-o", str(out)])
        == 0
    )
    assert main(["run", "--port", "sim://", "--frames", "2", "--background", SUBSET]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith(
        "an .npz archive; a background is a .npy capture (`spiel-edge background -o bg.npy`) or a spiel-csv frames file"
    )
