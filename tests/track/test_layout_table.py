"""The tracker's arrays are laid out as its tables (track/layout.py STATE, SCRATCH) say."""

import numpy as np

from spiel_edge.track import layout as L


def _at(view: np.ndarray, base: np.ndarray) -> int:
    start = view.__array_interface__["data"][0] - base.__array_interface__["data"][0]
    return start // base.itemsize


def test_the_views_are_where_the_tables_say():
    floats, ints, bools = L.allocate(L.SLOTS, np.zeros(L.N_PARAMS))
    for dtype, array in ((np.float64, floats), (np.int64, ints), (np.bool_, bools)):
        assert array.size == L.STATE.total(dtype) + L.SCRATCH.total(dtype)
    x, p, meta, counters = L.state_views(floats, ints)
    xm, pm, mu = L.model_views(floats, L.SLOTS)
    for name, view, base in (
        ("x", x, floats),
        ("p", p, floats),
        ("xm", xm, floats),
        ("pm", pm, floats),
        ("mu", mu, floats),
        ("meta", meta, ints),
        ("counters", counters, ints),
    ):
        field = L.STATE.fields[L.STATE.slot(name)]
        assert _at(view, base) == L.STATE.offset(name) and view.shape == field.dims, name
    z, r = L.measurement_views(floats)
    assert _at(z, floats) == L._F_SCRATCH + L.SCRATCH.offset("z") and z.shape == (L.SLOTS, 3)
    assert _at(r, floats) == L._F_SCRATCH + L.SCRATCH.offset("zr")
    assert L.SCRATCH.end("zr") == L.SCRATCH.total(np.float64)  # the targets come last
    floats[L._F_SCRATCH + L.SCRATCH.offset("snapshot")] = 7.0
    assert L.snapshot_rows(floats, 1)[0, 0] == 7.0
    ints[L._I_SCRATCH + L.SCRATCH.offset("target_slot")] = 5
    assert L.target_ids(ints, 1) == [5]
