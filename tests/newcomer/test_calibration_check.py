"""A calibration that cannot make things worse silently: before/after on positions it did
not fit, refusal (``--force`` overrides), a report, and ``--plot`` checked before any work."""

from __future__ import annotations

import sys
from importlib import resources

import numpy as np
import pytest

from spiel_edge.calibrate.validate import ErrorFigures, Validation, position_folds
from spiel_edge.cli import main

SUBSET = str(resources.files("spiel_edge") / "data" / "spiel_icra23_subset.npz")


@pytest.fixture
def wrong_delays(tmp_path):
    """A start whose delays are off by a sample on two channels: calibration must help."""
    path = tmp_path / "wrong.toml"
    path.write_text("[geometry]\ndelay_samples = [3.124, 0.605, 2.956, 1.741]\n")
    return path


def test_folds_keep_every_height_of_a_position_together():
    truth = np.array([[x, y, z] for x in (0, 10, 20) for y in (0, 5) for z in (100, 180, 220)])
    fold, k = position_folds(truth, 4)
    assert k == 4
    for xy in {tuple(t[:2]) for t in truth}:
        same = np.all(truth[:, :2] == xy, axis=1)
        assert len(set(fold[same])) == 1
    assert set(fold) == {0, 1, 2, 3}
    assert position_folds(truth[:3], 5)[1] == 1  # one position: nothing to hold out


def _figures(errors, acquisitions=None):
    return ErrorFigures(list(errors), acquisitions or len(errors))


def test_worse_is_a_higher_median_or_fewer_fixes():
    def v(before, after):
        return Validation(5, 10, before, after, _figures([1.0]), _figures([1.0]))

    assert v(_figures([10.0]), _figures([12.0])).worse
    assert not v(_figures([10.0]), _figures([9.0])).worse
    assert not v(_figures([10.0, 10.0, 10.0]), _figures([8.0, 8.0, 300.0])).worse  # one outlier
    assert v(_figures([10.0] * 10), _figures([9.0] * 5, 10)).worse  # half the fixes lost


def test_a_worse_calibration_is_refused(tmp_path, capsys):
    out, report = tmp_path / "cal.toml", tmp_path / "cal.txt"
    rc = main(["calibrate", "--recordings", SUBSET, "-o", str(out), "--report", str(report)])
    err = capsys.readouterr().err
    assert rc == 1 and not out.exists()
    assert "on positions it did not fit (25 (x, y) positions in 5 folds" in err
    assert "verdict: WORSE" in err and "not written" in err
    text = report.read_text()
    assert text.startswith("calibration report: 225 acquisitions") and "verdict: WORSE" in text
    assert main(["calibrate", "--recordings", SUBSET, "-o", str(out), "--force"]) == 0
    assert out.is_file() and "# on positions it did not fit" in out.read_text()
    assert "written to" in capsys.readouterr().err


def test_without_output_it_only_reports(capsys):
    assert main(["calibrate", "--recordings", SUBSET]) == 0
    assert "nothing was to be written" in capsys.readouterr().err


def test_a_calibration_that_helps_is_written(tmp_path, wrong_delays, capsys):
    out = tmp_path / "cal.toml"
    args = ["calibrate", "--recordings", SUBSET, "--calibration", str(wrong_delays)]
    rc = main([*args, "--fix", "receivers", "--fix", "emitter", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 0 and out.is_file(), err
    assert "verdict: better on positions it did not fit" in err
    line = next(x for x in err.splitlines() if x.startswith("on positions it did not fit"))
    before, after = (
        float(v) for v in __import__("re").findall(r"([\d.]+) mm (?:before|after)", line)
    )
    assert after < before / 2  # the wrong delays cost tens of mm; the calibration finds them


def test_plot_without_matplotlib_fails_before_anything(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    out, plot = tmp_path / "cal.toml", tmp_path / "cal.png"
    rc = main(["calibrate", "--recordings", SUBSET, "--force", "-o", str(out), "--plot", str(plot)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "'plot' extra" in err[0] and "spiel-edge[plot]" in err[0]
    assert not out.exists() and not plot.exists()


def test_cross_validation_takes_one_background_for_all():
    from spiel_edge.calibrate import calibrate_echoes, extract_echoes
    from spiel_edge.calibrate.validate import cross_validate
    from spiel_edge.data import load_subset
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import load_profile

    data = load_subset()
    keep = data.truth_mm[:, 2] == 100.0
    frames, truth = data.frames[keep], data.truth_mm[keep]
    bg = data.backgrounds[keep]
    profile = load_profile()
    candidates = extract_echoes(profile, frames, bg)

    def solve(mask):
        return calibrate_echoes(
            candidates[mask], truth[mask], profile, fix={"receivers", "emitter"}
        ).geometry

    every = cross_validate(
        profile, solve(truth[:, 0] == truth[:, 0]), frames, bg, truth, solve, build_pipeline
    )
    shared = cross_validate(profile, profile.geometry, frames, bg[0], truth, solve, build_pipeline)
    assert every.folds == shared.folds == 5 and every.positions == 25
    assert len(every.before.errors_mm) == every.before.fixes > 60
    assert shared.before.acquisitions == len(frames)
