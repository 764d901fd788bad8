"""The learned ToA correction is the real board's: left out on the virtual board's echo model."""

from __future__ import annotations

import pytest

from spiel_edge.cli import main
from spiel_edge.device import DeviceSession
from spiel_edge.link.sim_options import modelled_envelope
from spiel_edge.recordings.mcap_reader import recording_metadata
from spiel_edge.runtime.loop import live_toa_correction, open_pipeline


@pytest.mark.parametrize(
    ("url", "modelled"),
    [
        ("sim://?scene=model", True),
        ("SIM://a?scene=model&movers=3", True),
        ("sim://", False),  # the replayed recordings: the real board's envelopes
        ("sim://?scene=replay", False),
        ("sim://?scene=model&nonsense=1", False),  # a bad URL fails later, with its own error
        ("/dev/ttyACM0", False),
        ("usb://1209:5350", False),
    ],
)
def test_modelled_envelope_is_the_model_scene_only(url, modelled):
    assert modelled_envelope(url) is modelled


@pytest.mark.parametrize(
    ("url", "requested", "chosen"),
    [
        ("sim://?scene=model", None, "none"),
        ("sim://?scene=model", "auto", "auto"),  # asked for: kept
        ("sim://", None, None),  # None: the profile's
        ("/dev/ttyACM0", None, None),
        ("/dev/ttyACM0", "none", "none"),
    ],
)
def test_live_toa_correction(url, requested, chosen):
    assert live_toa_correction(url, requested) == chosen


@pytest.mark.parametrize(
    ("query", "requested", "corrected"),
    [("scene=model", None, False), ("scene=model", "auto", True), ("scene=replay", None, True)],
)
def test_open_pipeline_leaves_the_correction_out_on_the_model_unless_asked(
    sim_url, query, requested, corrected
):
    session = DeviceSession(sim_url(query), reconnect=False)
    try:
        pipeline, _ = open_pipeline(session, "spiel-icra23", toa_correction=requested)
    finally:
        session.close()
    staged = getattr(pipeline, "pipeline", pipeline)  # the fused pipeline wraps the staged one
    assert (staged.echo_timing.correction is not None) is corrected


def test_a_recording_names_the_correction_only_when_it_is_not_the_profiles(sim_url, tmp_path):
    """So that replaying a real board's recording with another profile takes that profile's."""
    for query, expected in (("", None), ("scene=model", "none")):
        rec = tmp_path / f"run{len(query)}.mcap"
        argv = ["run", "--port", sim_url(query), "--frames", "3", "--rate", "200"]
        assert main([*argv, "--record", str(rec), "-o", str(rec.with_suffix(".ndjson"))]) == 0
        assert recording_metadata(rec).get("toa_correction") == expected
