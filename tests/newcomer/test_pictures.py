"""Pictures: each one rendered and its content checked (not blank, the right size, echo marks
where the records put them); without matplotlib, one line naming the extra."""

from __future__ import annotations

import json
import sys
from importlib import resources

import numpy as np
import pytest

from spiel_edge.cli import main

SUBSET = str(resources.files("spiel_edge") / "data" / "spiel_icra23_subset.npz")
mpl_image = pytest.importorskip("matplotlib.image", reason="matplotlib is the 'plot' extra")


def _png(path):
    img = mpl_image.imread(str(path))  # (rows, columns, RGBA) floats in 0-1
    assert img.ndim == 3 and img.shape[2] in (3, 4)
    rgb = img[:, :, :3]
    assert rgb.std() > 0.05, "blank picture"
    return rgb


def _red_columns(rgb):
    red = (rgb[:, :, 0] > 0.9) & (rgb[:, :, 1] < 0.15) & (rgb[:, :, 2] < 0.15)
    return red.sum(axis=0)  # red pixels per column


def test_ascan_marks_every_echo_where_the_record_puts_it(tmp_path):
    from spiel_edge.data import load_subset
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import load_profile
    from spiel_edge.view.ascan import draw_ascan

    data = load_subset()
    pipeline = build_pipeline(load_profile(), fused=False)
    i = 5
    out = tmp_path / "a.png"
    drawn = draw_ascan(pipeline, data.frames[i], data.backgrounds[i], out)
    rgb = _png(out)
    assert (rgb.shape[1], rgb.shape[0]) == drawn["size"] == (1000, 700)
    record = build_pipeline(load_profile()).process(data.frames[i], data.backgrounds[i]).record()
    assert [[round(t, 3) for t in ch] for ch in drawn["echoes"]] == record["echoes"]
    columns = _red_columns(rgb)
    unmatched = [x for ch in drawn["marks"] for x, matched in ch if not matched]
    assert unmatched, "this acquisition has unmatched echoes"
    for x in unmatched:  # a red vertical line at the echo's time (to a pixel)
        assert columns[int(round(x)) - 1 : int(round(x)) + 2].max() > 50, x
    marked = set(np.flatnonzero(columns > 50))
    near = {c for x in unmatched for c in range(int(round(x)) - 2, int(round(x)) + 3)}
    assert marked <= near  # no red line where no unmatched echo is


def test_view_ascan_command(tmp_path, capsys):
    out = tmp_path / "a.png"
    assert main(["view", "ascan", SUBSET, "--index", "3", "-o", str(out)]) == 0
    assert _png(out).shape[:2] == (700, 1000)
    assert "echoes on 4 channels" in capsys.readouterr().err
    assert main(["view", "ascan", SUBSET, "--index", "999", "-o", str(out), "--force"]) == 2
    assert "has no acquisition 999 (it holds 228)" in capsys.readouterr().err


def test_view_positions_draws_targets_ellipses_tracks_and_truth(tmp_path, capsys):
    records = tmp_path / "scene.ndjson"
    args = ["run", "--port", "sim://?scene=model&movers=2&seed=1", "--frames", "30"]
    assert main([*args, "--max-targets", "4", "-o", str(records)]) == 0
    from spiel_edge.view.positions import draw_positions, read_records

    recs = read_records(records)
    out = tmp_path / "p.png"
    drawn = draw_positions(recs, out)
    want = sum(len(r["targets"]) for r in recs)
    assert drawn["targets"] == want == drawn["ellipses"] and drawn["tracks"] >= 1
    rgb = _png(out)
    assert (rgb.shape[1], rgb.shape[0]) == drawn["size"] == (1200, 550)
    assert main(["view", "positions", str(records), "-o", str(tmp_path / "q.png")]) == 0
    assert f"{want} targets" in capsys.readouterr().err


def test_view_positions_refuses_what_is_not_records(tmp_path, capsys):
    bad = tmp_path / "x.ndjson"
    bad.write_text('{"seq": 1}\nnot json\n')
    assert main(["view", "positions", str(bad), "-o", str(tmp_path / "p.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "x.ndjson:2: not a JSON record" in err[0]


def test_evaluate_plot_is_error_by_position(tmp_path, capsys):
    out = tmp_path / "e.png"
    assert main(["evaluate", SUBSET, "--json", "--plot", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out)
    rgb = _png(out)
    assert rgb.shape[:2] == (450, 1450)  # three heights
    assert summary["frames"] == 150


def test_calibrate_plot_has_the_before_after_panel(tmp_path, capsys):
    out = tmp_path / "c.png"
    assert main(["calibrate", "--recordings", SUBSET, "--plot", str(out)]) == 0
    rgb = _png(out)
    assert rgb.shape[:2] == (500, 1650)  # geometry, residuals, error before/after


@pytest.mark.parametrize(
    "args",
    [
        ["view", "ascan", SUBSET],
        ["view", "positions", SUBSET],
        ["evaluate", SUBSET, "--plot", "e.png"],
    ],
)
def test_without_matplotlib_one_line_names_the_extra(tmp_path, capsys, monkeypatch, args):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'plot' extra" in err[0], err
    assert not list(tmp_path.iterdir())  # nothing written
