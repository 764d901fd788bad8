"""One- and two-transducer boards (pipeline/ranging.py): range, bearing, I/Q timing, the
MEMG window from the profile, and the sensor_msgs/Range they publish; synthetic frames only."""

from __future__ import annotations

import dataclasses
import math
import struct

import numpy as np
import pytest
from scipy.special import erf

from spiel_edge.errors import ConfigError
from spiel_edge.messages import ros2_messages as rm
from spiel_edge.messages.ros2_limits import SensorLimits
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.pipeline.ranging import (
    REASON_NO_ECHO,
    REASON_RANGE_ONLY,
    RangePipeline,
    iq_refine,
    pair_plane,
    solve_pair,
    toa_sigma,
)
from spiel_edge.pipeline.stages.detect import detect
from spiel_edge.pipeline.stages.memg import fit_memg, memg_kernel
from spiel_edge.profile.schema import load_profile, profile_from_dict, profile_to_dict


def emg(t, alpha, mu, sigma, eta):
    u = (t - mu) / sigma
    return alpha * np.exp(-0.5 * u * u) * (1.0 + erf(eta * u / math.sqrt(2.0)))


def emg_mode(mu, sigma, eta):
    grid = np.linspace(mu - 3, mu + 6, 90001)
    return float(grid[np.argmax(emg(grid, 1.0, mu, sigma, eta))])


def half_max_time(mu, sigma, eta):
    """Where the rising edge of the echo reaches half its maximum (the "half" ToA)."""
    grid = np.linspace(mu - 6, mu + 6, 120001)
    values = emg(grid, 1.0, mu, sigma, eta)
    peak = np.argmax(values)
    return float(grid[:peak][np.argmin(np.abs(values[:peak] - values[peak] / 2))])


def echo_frame(n, mu, alpha=1500.0, sigma=1.6, eta=1.2, noise=0.0, seed=0):
    t = np.arange(n, dtype=np.float64)
    rng = np.random.default_rng(seed)
    return emg(t, alpha, mu, sigma, eta) + noise * rng.standard_normal(n)


def test_one_transducer_gives_its_range_and_variance():
    profile = load_profile("ch101-one")
    pipe = build_pipeline(profile)
    assert isinstance(pipe, RangePipeline)
    mu = 30.3
    frame = echo_frame(64, mu)[None, :]
    result = pipe.process(frame)
    record = result.record()
    mode = emg_mode(mu, 1.6, 1.2)
    expected = (mode - profile.geometry.delays()[0]) * profile.mm_per_sample / 2.0
    assert record["reason"] == REASON_RANGE_ONLY and record["position_mm"] is None
    assert record["range_mm"] == pytest.approx(expected, abs=0.05)
    sigma = profile.ranging.envelope_sigma[0] * profile.mm_per_sample / 2.0
    assert record["range_var_mm2"] == pytest.approx(sigma**2, rel=1e-3)
    assert record["timing"] == "envelope" and record["matched"] == [0]


def test_the_first_or_the_strongest_echo():
    profile = load_profile("ch101-one")
    frame = (echo_frame(64, 22.0, alpha=400.0) + echo_frame(64, 40.0, alpha=1500.0))[None, :]
    first = build_pipeline(profile).process(frame).record()
    strongest = (
        build_pipeline(
            profile.replace(ranging=dataclasses.replace(profile.ranging, echo="strongest"))
        )
        .process(frame)
        .record()
    )
    assert first["range_mm"] < strongest["range_mm"] - 20


def test_no_echo_and_flat_frames_say_why():
    pipe = build_pipeline(load_profile("ch101-one"))
    rec = pipe.process(np.zeros((1, 64))).record()
    assert rec["range_mm"] is None and "flat" in rec["reason"]
    rec = pipe.process(echo_frame(64, 30.0, alpha=5.0, noise=1.0)[None, :]).record()
    assert rec["range_mm"] is None and rec["reason"] == REASON_NO_ECHO


def _paths(profile, point):
    g = profile.geometry
    return g.echo_paths_mm(point)


def test_two_transducers_give_range_and_bearing_in_their_plane():
    profile = load_profile("ch101-pair")
    pipe = build_pipeline(profile)
    point = np.array([60.0, 0.0, 200.0])  # in the x-z plane of the pair
    paths = _paths(profile, point)
    mmps = profile.mm_per_sample
    shapes = (1.6, 1.2)
    modes = paths / mmps + profile.geometry.delays()
    frames = np.stack(
        [
            echo_frame(64, m - (emg_mode(0.0, *shapes)), sigma=shapes[0], eta=shapes[1])
            for m in modes
        ]
    )
    record = pipe.process(frames).record()
    assert record["reason"] is None
    np.testing.assert_allclose(record["position_mm"], point, atol=1.0)
    assert record["range_mm"] == pytest.approx(np.linalg.norm(point), abs=0.5)
    # the pair's midpoint sees the target at atan2(x - 37.5, z)
    assert record["bearing_deg"] == pytest.approx(math.degrees(math.atan2(60 - 37.5, 200)), abs=0.5)
    assert record["bearing_var_deg2"] > 0
    cov = np.array(record["targets"][0]["covariance_mm2"])
    assert np.all(np.linalg.eigvalsh(cov) > -1e-9)
    assert cov[1, 1] > cov[0, 0]  # out of the plane (y) it is wide


def test_pair_solve_against_a_direct_least_squares():
    receivers = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0]])
    emitter = np.zeros(3)
    plane = pair_plane(receivers, np.array([0.0, 0.0, 1.0]))
    for point in ([-30.0, 0.0, 150.0], [120.0, 0.0, 90.0]):
        p = np.array(point)
        paths = np.linalg.norm(p - emitter) + np.linalg.norm(p - receivers, axis=1)
        pos, cov, bearing, bvar, r, rvar = solve_pair(
            paths, np.array([0.5, 0.5]), receivers, emitter, plane, 0.5
        )
        np.testing.assert_allclose(pos, p, atol=1e-6)
        assert r == pytest.approx(np.linalg.norm(p), rel=1e-9)
        # the covariance by finite differences of the inverse map
        eps = 1e-4
        jac = np.empty((2, 2))
        for j in range(2):
            d = np.zeros(2)
            d[j] = eps
            moved = solve_pair(paths + d, np.ones(2), receivers, emitter, plane, 0.5)[0]
            jac[:, j] = (moved[[0, 2]] - pos[[0, 2]]) / eps
        np.testing.assert_allclose(cov[np.ix_([0, 2], [0, 2])], 0.25 * jac @ jac.T, rtol=1e-4)


def iq_pairs(n, mu, cycles_per_sample, phase0, alpha=2000.0, sigma=1.6, eta=1.2):
    """(q, i) interleaved baseband of an echo whose mode is at ``mode`` samples: magnitude an
    EMG, phase phase0 - 2 pi f x mode (a pure delay)."""
    amp = echo_frame(n, mu, alpha, sigma, eta)
    mode = emg_mode(mu, sigma, eta)
    phi = phase0 - 2.0 * math.pi * cycles_per_sample * mode
    out = np.empty(2 * n)
    out[0::2], out[1::2] = amp * math.sin(phi), amp * math.cos(phi)
    return out, mode


def test_iq_refine_takes_the_wrap_from_the_envelope():
    f = 2.0  # fs = carrier / 2: one wrap per 0.5 sample
    pairs, mode = iq_pairs(128, 70.3, f, 0.7)
    q, i = pairs[0::2], pairs[1::2]
    none = (0.0, 0.0)
    for error in (-0.2, 0.0, 0.15, 0.24):
        assert iq_refine(mode + error, i, q, f, 0.7, none, 0.0) == pytest.approx(mode, abs=1e-9)
    # beyond half a wrap the neighbouring wrap is taken: the envelope decides
    assert iq_refine(mode + 0.3, i, q, f, 0.7, none, 0.0) == pytest.approx(mode + 0.5, abs=1e-9)
    # near the boundary, with a margin: not trusted
    assert iq_refine(mode + 0.2, i, q, f, 0.7, none, 0.2) is None
    assert iq_refine(mode + 0.05, i, q, f, 0.7, none, 0.2) == pytest.approx(mode, abs=1e-9)
    # an envelope that reads late by a + b t: the drift model brings its wrap back
    drift = (0.1, 0.3 / 70.0)
    late = mode + drift[0] + drift[1] * (mode + 0.4)
    assert iq_refine(late, i, q, f, 0.7, none, 0.0) == pytest.approx(mode + 0.5, abs=1e-9)
    assert iq_refine(late, i, q, f, 0.7, drift, 0.0) == pytest.approx(mode, abs=1e-9)


def test_dk_ch101_profile_times_iq_frames_by_the_carrier_phase():
    profile = load_profile("dk-ch101-gpr-sr-narrow")
    # the envelope's mode (the synthetic echo's phase is a pure delay of its mode)
    memg = dataclasses.replace(profile.memg, toa="mode", window_before=5, window_after=6)
    ranging = dataclasses.replace(profile.ranging, timing="iq", iq_drift_samples=(0.0, 0.0))
    profile = profile.replace(memg=memg, ranging=ranging)
    assert profile.acquisition.sample_rate_hz * 2 == pytest.approx(profile.acquisition.carrier_hz)
    f = profile.acquisition.carrier_hz / profile.acquisition.sample_rate_hz
    offset = profile.ranging.iq_phase_offset_rad
    pairs, mode = iq_pairs(128, 70.2, f, offset)
    pipe = build_pipeline(profile)
    record = pipe.process(pairs[None, :]).record()
    assert record["timing"] == "iq"
    mmps = profile.mm_per_sample * profile.ranging.range_scale
    expected = (mode - profile.geometry.delays()[0]) * mmps / 2.0
    assert record["range_mm"] == pytest.approx(expected, abs=0.005)
    iq_std = toa_sigma(profile.ranging.iq_sigma, 2000.0, expected, 1.0) * mmps / 2
    assert record["range_var_mm2"] == pytest.approx(iq_std**2, rel=0.02)
    # amplitudes from a board that keeps the phase apart: the envelope times them
    amplitude = np.hypot(pairs[0::2], pairs[1::2])[None, :]
    assert pipe.process(amplitude).record()["timing"] == "envelope"
    with pytest.raises(Exception, match="expects"):
        pipe.process(np.zeros((1, 100)))


def test_memg_window_from_the_profile():
    y = np.stack([echo_frame(128, 40.0, sigma=3.0, eta=2.0, noise=5.0, seed=3)])
    peaks, counts = detect(y, threshold=30.0, min_amplitude=100.0, max_echoes=4)
    default = fit_memg(y, peaks, counts)
    # the default window is the compiled kernel's; the windowed path fits it the same
    from spiel_edge.pipeline.stages import memg

    same = np.full_like(default, np.nan)
    memg._fit_windowed(y, peaks, counts, 3.0, 30, (5, 6), same)
    np.testing.assert_array_equal(same, default)
    reference = np.full_like(default, np.nan)
    memg_kernel(y, peaks, counts, 3.0, 30, reference, np.zeros(peaks.shape, dtype=np.int64))
    np.testing.assert_array_equal(reference, default)
    wide = fit_memg(y, peaks, counts, window_before=8, window_after=14)
    assert not np.array_equal(wide, default)
    # the wide window sees the whole skewed echo: its fit is nearer the truth (sigma 3, eta 2)
    assert abs(wide[0, 0, 2] - 3.0) < abs(default[0, 0, 2] - 3.0) + 0.05
    with pytest.raises(Exception, match="window"):
        fit_memg(y, peaks, counts, window_before=0)


def _with(profile, **sections):
    data = profile_to_dict(profile)
    for key, values in sections.items():
        data[key] = {**data[key], **values}
    return profile_from_dict(data)


def test_profile_rules_for_few_transducers():
    one = load_profile("ch101-one")
    with pytest.raises(ConfigError, match="needs acquisition.signal = 'iq'"):
        _with(one, ranging={"timing": "iq"})
    with pytest.raises(ConfigError, match="memg.window_before"):
        _with(one, memg={"window_before": 0})
    with pytest.raises(ConfigError, match="at least 1 listening"):
        _with(one, geometry={"listening": [False]})
    pair = load_profile("ch101-pair")
    with pytest.raises(ConfigError, match="baseline"):
        _with(pair, geometry={"facing": [1.0, 0.0, 0.0]})
    icra = load_profile("spiel-icra23")
    # four with I/Q: the 3-D pipeline timed by the carrier phase (tests/core/test_iq3d.py)
    assert build_pipeline(_with(icra, acquisition={"signal": "iq"})).takes_iq
    # three or more: a window other than the default runs the staged path, not the compiled one
    wide = _with(icra, memg={"window_before": 7})
    assert build_pipeline(wide).pipeline.kernel_constants() is None
    assert build_pipeline(icra).pipeline.kernel_constants() is not None


def _decode_range(data: bytes) -> tuple[float, float, float, float]:
    (n,) = struct.unpack_from("<I", data, 12)
    at = 16 + n + 1
    at += -(at - 4) % 4
    fov, lo, hi, value, var = struct.unpack_from("<5f", data, at)
    return value, var, lo, hi


def test_ros2_range_message_carries_a_ranging_record():
    settings = type("S", (), {"limits": SensorLimits(math.pi, 0.05, 0.25)})()
    messages = rm.Ros2Messages(settings)
    record = {"position_mm": None, "targets": [], "range_mm": 150.0, "range_var_mm2": 0.04}
    out = dict(messages.of_record(record))
    value, var, lo, hi = _decode_range(out["range"])
    assert value == pytest.approx(0.150, rel=1e-6) and var == pytest.approx(0.04e-6, rel=1e-5)
    assert (lo, hi) == pytest.approx((0.05, 0.25), rel=1e-6)
    far = dict(messages.of_record({**record, "range_mm": 400.0}))
    assert math.isinf(_decode_range(far["range"])[0])
    none = dict(messages.of_record({"position_mm": None, "targets": []}))
    assert math.isinf(_decode_range(none["range"])[0])


def test_error_model_per_echo_grows_as_the_echo_weakens():
    model = (0.05, 60.0, 0.3, 2.0)
    assert toa_sigma(model, 600.0, 0.0, 1.0) == pytest.approx(math.hypot(0.05, 0.1))
    assert toa_sigma(model, 600.0, 100.0, 1.0) == pytest.approx(math.sqrt(0.05**2 + 0.01 + 0.09))
    assert toa_sigma(model, 600.0, 0.0, 0.5) == pytest.approx(math.sqrt(0.05**2 + 0.01 + 1.0))
    profile = load_profile("ch101-one")
    ranging = dataclasses.replace(profile.ranging, envelope_sigma=(0.05, 60.0, 0.0, 0.0))
    pipe = build_pipeline(profile.replace(ranging=ranging))
    strong = pipe.process(echo_frame(64, 30.0, alpha=3000.0)[None, :]).record()
    weak = pipe.process(echo_frame(64, 30.0, alpha=300.0)[None, :]).record()
    assert weak["range_var_mm2"] > 4 * strong["range_var_mm2"]


def test_data_peak_finds_the_echo_maximum_after_its_leading_edge():
    from spiel_edge.pipeline.ranging import data_peak
    from spiel_edge.pipeline.stages.features import interpolated_peak

    y = echo_frame(128, 60.3, sigma=2.0, eta=1.5)
    mode = emg_mode(60.3, 2.0, 1.5)
    edge = half_max_time(60.3, 2.0, 1.5)
    got = data_peak(y, edge, 7)
    assert got == pytest.approx(mode, abs=0.1)  # a parabola through sampled points
    assert got == interpolated_peak(y, int(np.argmax(y)))  # the features' "peak" ToA
    assert 126.0 <= data_peak(y, 126.5, 7) <= 127.0  # at the frame's end: inside it
