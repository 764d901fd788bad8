"""The SToF-Chirp layout as a recording format (recordings/stof_chirp.py): replay and evaluate
of synthetic sequence folders written in the dataset's layout (the data itself is never
needed: it has no licence)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from spiel_edge.cli import main
from spiel_edge.errors import ConfigError
from spiel_edge.profile.schema import load_profile
from spiel_edge.recordings.stof_chirp import (
    find_specs,
    frame_numbers,
    profile_for_specs,
    read_specs,
    read_stof_frame,
    truth_mm,
)
from tests.core.test_ranging import emg_mode, half_max_time, iq_pairs

SHIFT = emg_mode(0.0, 1.6, 1.2)  # mode - mu of the synthetic echoes
HALF = half_max_time(0.0, 1.6, 1.2)  # its leading edge's half maximum - mu

SPECS = """# sensor header information
manufacturer: tdk
model: dk-ch101
firmware: gpr_sr_narrow_gpr-101_v43a
fhz_carrier: 175980
fhz_sample: 87990
DATA_MAX_NUM_SAMPLES: 128
READ_IQ_DATA: True

# other information
temperature: 21"""


def write_dataset(root, distances_mm=(150.0, 190.0), frames=5, seed=0):
    """root/sensor_specs.yaml, root/train/<d>/NN_{envelope,iq}_frame.txt and the truth table:
    echoes whose envelope ToA and phase are where the built-in profile puts each distance."""
    rng = np.random.default_rng(seed)
    (root / "train").mkdir(parents=True)
    (root / "sensor_specs.yaml").write_text(SPECS)
    (root / "truth").mkdir()
    profile = profile_for_specs(read_specs(root / "sensor_specs.yaml"))
    f = profile.acquisition.carrier_hz / profile.acquisition.sample_rate_hz
    mmps = profile.mm_per_sample
    rows = []
    for d, mm in enumerate(distances_mm):
        rows.append(f"{d},{mm},mm")
        seq = root / "train" / str(d)
        seq.mkdir()
        for k in range(frames):
            # the profile's envelope ToA mixes the half maximum and the peak (the mode)
            w = profile.ranging.peak_weight
            toa = 2 * mm / (mmps * profile.ranging.range_scale) + profile.geometry.delays()[0]
            mu = toa - ((1 - w) * HALF + w * SHIFT) + 0.02 * rng.standard_normal()
            # the phase of a delay whose phase time is the ToA (as the fitted offset makes it)
            phase0 = profile.ranging.iq_phase_offset_rad + 2 * math.pi * f * (mu + SHIFT - toa)
            pairs, _ = iq_pairs(128, mu, f, phase0)
            q, i = pairs[0::2], pairs[1::2]
            iq = np.vstack([np.column_stack([i, q]), [[0.0, 0.0]]])  # one row more
            np.savetxt(seq / f"{k:02d}_iq_frame.txt", iq)
            np.savetxt(seq / f"{k:02d}_envelope_frame.txt", np.hypot(i, q))
    (root / "truth" / "true_measurement_positions.csv").write_text("\n".join(rows) + "\n")
    return profile


def test_reader_layout(tmp_path):
    profile = write_dataset(tmp_path, frames=12)
    seq = tmp_path / "train" / "0"
    assert frame_numbers(seq) == [f"{k:02d}" for k in range(12)]  # frame order, 10 after 09
    assert find_specs(seq) == (tmp_path / "sensor_specs.yaml").resolve()
    assert truth_mm(seq) == 150.0
    iq = read_stof_frame(seq, "03", iq=True)
    env = read_stof_frame(seq, "03", iq=False)
    assert iq.shape == (1, 256) and env.shape == (1, 128)
    np.testing.assert_allclose(np.hypot(iq[0, 0::2], iq[0, 1::2]), env[0], rtol=1e-6)
    # the board of the specs, at the speed of sound of their temperature
    assert profile.name == "dk-ch101-gpr-sr-narrow"
    assert profile.geometry.speed_of_sound_m_s == pytest.approx(331.4 + 0.6 * 21)


def test_specs_of_another_board_are_refused(tmp_path):
    (tmp_path / "sensor_specs.yaml").write_text(SPECS.replace("128", "64"))
    with pytest.raises(ConfigError, match="no built-in profile"):
        profile_for_specs(read_specs(tmp_path / "sensor_specs.yaml"))
    (tmp_path / "sensor_specs.yaml").write_text(SPECS.replace("87990", "44000"))
    with pytest.raises(ConfigError, match="fhz_sample"):
        profile_for_specs(read_specs(tmp_path / "sensor_specs.yaml"))


def test_replay_writes_one_record_with_a_range_per_frame(tmp_path):
    write_dataset(tmp_path / "data", frames=7)
    seq = tmp_path / "data" / "train" / "1"
    (seq / "03_iq_frame.txt").write_text("1 2\nnot numbers\n")  # a damaged frame
    out = tmp_path / "out.ndjson"
    assert main(["replay", str(seq), "--format", "stof-chirp", "-o", str(out)]) == 1  # one bad
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["source"] for r in records] == [f"{k:02d}" for k in range(7)]
    good = [r for r in records if r["source"] != "03"]
    assert all(r["range_mm"] is not None and r["timing"] == "iq" for r in good)
    assert all(abs(r["range_mm"] - 190.0) < 0.5 for r in good)
    assert "03" in records[3]["error"]
    # the format is recognised without --format
    out2 = tmp_path / "out2.ndjson"
    (seq / "03_iq_frame.txt").unlink()
    (seq / "03_envelope_frame.txt").unlink()
    assert main(["replay", str(seq), "-o", str(out2)]) == 0
    assert len(out2.read_text().splitlines()) == 6


def test_evaluate_reports_range_metrics(tmp_path, capsys):
    write_dataset(tmp_path, frames=6)
    assert main(["evaluate", str(tmp_path / "train"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 12 and summary["with_range"] == 1.0
    assert summary["mae_mm"] < 0.1 and summary["over_1mm"] == 0.0
    assert set(summary["by_distance"]) == {"150", "190"}
    assert summary["timing"] == {"iq": 12}
    assert 0.0 <= summary["coverage95"] <= 1.0
    assert not math.isnan(summary["rms_std_mm"])


def test_envelope_profile_reads_the_envelope_files(tmp_path):
    write_dataset(tmp_path, frames=3)
    profile = load_profile("dk-ch101-gpr-sr-narrow")
    env_profile = tmp_path / "env.toml"
    text = (
        load_profile.__globals__["resources"].files("spiel_edge")
        / "profile"
        / "builtin"
        / "dk-ch101-gpr-sr-narrow.toml"
    ).read_text()
    env_profile.write_text(
        text.replace('signal = "iq"', 'signal = "envelope"').replace(
            'timing = "iq"', 'timing = "envelope"'
        )
    )
    out = tmp_path / "o.ndjson"
    assert (
        main(
            ["replay", str(tmp_path / "train" / "0"), "--profile", str(env_profile), "-o", str(out)]
        )
        == 0
    )
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 3 and all(r["timing"] == "envelope" for r in records)
    assert profile.name == "dk-ch101-gpr-sr-narrow"


def test_sequence_folders_of_a_dataset(tmp_path):
    from spiel_edge.errors import InputError
    from spiel_edge.recordings.stof_chirp import sequence_folders

    write_dataset(
        tmp_path,
        distances_mm=(150.0, 160.0, 170.0, 180.0, 190.0, 200.0, 210.0, 220.0, 230.0, 240.0, 250.0),
        frames=1,
    )
    np.savetxt(tmp_path / "truth" / "00_envelope_frame.txt", np.zeros(4))  # truth/ is left out
    found = sequence_folders(tmp_path)
    assert [p.name for p in found] == [str(d) for d in range(11)]  # 10 after 9
    assert sequence_folders(tmp_path / "train" / "3") == [tmp_path / "train" / "3"]
    deep = tmp_path / "a" / "b" / "c" / "d"
    deep.mkdir(parents=True)
    np.savetxt(deep / "00_envelope_frame.txt", np.zeros(4))
    with pytest.raises(InputError, match="no SToF-Chirp sequence"):
        sequence_folders(tmp_path / "a")  # three levels down: not walked
