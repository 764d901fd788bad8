"""Three or more listening channels with I/Q samples (pipeline/iq3d.py): detection, MEMG fit
and association on the pairs' magnitude as for an envelope board, each matched echo's ToA
refined by the carrier phase (the one-transducer code), its weight and the record's timing;
frames from the echo model and hand-made pairs only."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spiel_edge.errors import InputError
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.pipeline.iq3d import IqPipeline, baseband
from spiel_edge.pipeline.ranging import toa_sigma
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.profile.schema import load_profile, profile_from_dict, profile_to_dict
from spiel_edge.sim.scenes import EchoModelScene


@pytest.fixture
def quad():
    return load_profile("ch101-quad-iq")


def _with(profile, **sections):
    data = profile_to_dict(profile)
    for key, values in sections.items():
        data[key] = {**data[key], **values}
    return profile_from_dict(data)


def _scene_frame(profile, target, seed=0, noise=5.0):
    acq = profile.acquisition
    scene = EchoModelScene(
        profile.geometry,
        sample_rate_hz=acq.sample_rate_hz,
        n_samples=acq.n_samples,
        targets_mm=np.array([target]),
        noise=noise,
        seed=seed,
        carrier_hz=acq.carrier_hz,
    )
    frame = scene.frame(0, acq.n_samples, 0.0, iq=True)
    pairs = frame.iq.reshape(frame.iq.shape[0], -1).astype(np.float64)  # (q, i) interleaved
    return pairs, frame.samples.astype(np.float64), scene.background(acq.n_samples)


TARGETS = [(20.0, -10.0, 150.0), (-30.0, 25.0, 120.0), (0.0, 40.0, 180.0), (35.0, 5.0, 100.0)]


def test_iq_profile_builds_the_phase_timed_pipeline(quad):
    pipe = build_pipeline(quad)
    assert isinstance(pipe, IqPipeline) and pipe.takes_iq
    assert pipe.kernel_constants() is None  # the staged path: the kernels know no phase
    assert pipe.expected_shape() == (4, 256)
    with pytest.raises(InputError, match=r"expects \(4, 256\)"):
        pipe.process(np.zeros((4, 100)))
    with pytest.raises(InputError, match="background"):
        pipe.process(np.zeros((4, 256)), np.zeros((3, 256)))
    for bad in (np.nan, np.inf):  # one line, whatever the phase path would have made of it
        with pytest.raises(InputError, match="NaN or infinite"):
            pipe.process(np.full((4, 256), bad))
    assert pipe.process(np.zeros((4, 256))).record()["reason"].startswith("frame is flat")
    icra = load_profile("spiel-icra23")
    assert isinstance(build_pipeline(_with(icra, acquisition={"signal": "iq"})), IqPipeline)
    assert not isinstance(build_pipeline(icra), IqPipeline)


def test_carrier_phase_times_every_matched_echo(quad):
    pipe = build_pipeline(quad)
    mmps = quad.mm_per_sample
    errors = []
    for k, target in enumerate(TARGETS):
        pairs, _, background = _scene_frame(quad, target, seed=k)
        iq = pipe.process(pairs, background)
        amplitude = np.hypot(pairs[:, 0::2], pairs[:, 1::2])
        env = pipe.process(amplitude, background)
        record = iq.record()
        assert record["timing"] == "iq" and record["targets"][0]["timing"] == "iq"
        assert env.record()["timing"] == "envelope"
        # the echo model's phase is an exact delay: the phase times it to a hair, the envelope
        # (noisy magnitude) to tenths of a millimetre
        errors.append(
            (np.linalg.norm(iq.position_mm - target), np.linalg.norm(env.position_mm - target))
        )
        # its covariance is [ranging] iq_sigma's: sigma 0.02 samples on every echo path
        cov_iq, cov_env = iq.targets[0].covariance_mm2, env.targets[0].covariance_mm2
        assert np.trace(cov_iq) < np.trace(cov_env) / 20
        sigma = toa_sigma(quad.ranging.iq_sigma, 1.0, 150.0, 1.0) * mmps
        assert sigma == pytest.approx(0.02 * mmps)
    err_iq, err_env = np.array(errors).T
    assert err_iq.max() < 0.05 and err_iq.mean() < err_env.mean() / 3


def test_refined_toas_against_a_numpy_reference(quad):
    """The pipeline's per-echo ToAs against the phase written out in numpy: the angle of the
    complex baseband interpolated at the envelope ToA, the wrap nearest it."""
    pipe = IqPipeline(quad)
    f = quad.acquisition.carrier_hz / quad.acquisition.sample_rate_hz
    pairs, _, background = _scene_frame(quad, TARGETS[0], seed=3)
    env = pipe.envelope(pairs)
    seen = {}

    def spy(feats, matched, use, picked, weights, shift):
        out = IqPipeline.phase_timing(pipe, feats, matched, use, picked, weights, shift)
        seen.update(picked=picked.copy(), shift=np.broadcast_to(shift, picked.shape).copy())
        seen.update(out=out)
        return out

    pipe.phase_timing = spy
    pipe.process(pairs, background)
    z = pairs[:, 1::2] + 1j * pairs[:, 0::2]
    np.testing.assert_array_equal(baseband(pairs), z)
    t_env = seen["picked"] + seen["shift"]
    want = np.empty(4)
    for c in range(4):
        lo = int(np.floor(t_env[c]))
        w = t_env[c] - lo
        phase = np.angle((1 - w) * z[c, lo] + w * z[c, lo + 1])
        t_phase = -phase / (2 * np.pi * f)  # offset 0, no drift
        wrap = 1 / f
        want[c] = t_env[c] + (t_phase - t_env[c]) - wrap * np.round((t_phase - t_env[c]) / wrap)
    got, weights, shift, timing = seen["out"]
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert timing == "iq" and not np.any(shift)
    np.testing.assert_allclose(weights, 1 / 0.02)
    assert np.all(np.abs(got - t_env) <= 0.25 + 1e-12)  # within half a wrap of the envelope
    assert env.shape == (4, 128)


def test_amplitudes_run_as_an_envelope_board(quad):
    """Amplitudes, or pairs under a profile timed by the envelope, give exactly the records of
    the envelope board with the same settings (the pairs' magnitude is its envelope)."""
    twin = _with(quad, acquisition={"signal": "envelope"}, ranging={"timing": "envelope"})
    plain = build_pipeline(twin, fused=False)
    assert type(plain) is Pipeline
    pipe = build_pipeline(quad)
    by_envelope = build_pipeline(_with(quad, ranging={"timing": "envelope"}))
    for k, target in enumerate(TARGETS):
        pairs, _, background = _scene_frame(quad, target, seed=10 + k)
        amplitude = np.hypot(pairs[:, 0::2], pairs[:, 1::2])
        want = plain.process(amplitude, background).record()
        assert want["position_mm"] is not None
        for got in (pipe.process(amplitude, background), by_envelope.process(pairs, background)):
            record = got.record()
            assert record.pop("timing") == "envelope"
            for t in record["targets"]:
                assert t.pop("timing") == "envelope"
            assert record == want


def test_an_untrusted_wrap_keeps_the_envelope(quad):
    """A wrap margin near half a wrap trusts no phase: every echo keeps its envelope ToA."""
    wary = build_pipeline(_with(quad, ranging={"iq_wrap_margin": 0.499}))
    some = build_pipeline(_with(quad, ranging={"iq_wrap_margin": 0.3}))
    timings = set()
    for k, target in enumerate(TARGETS):
        pairs, _, background = _scene_frame(quad, target, seed=20 + k)
        assert wary.process(pairs, background).record()["timing"] == "envelope"
        timings.add(some.process(pairs, background).record()["timing"])
    assert timings <= {"iq", "mixed", "envelope"} and len(timings) >= 1


def test_background_pairs_are_subtracted_in_the_complex_domain(quad):
    """A static echo overlapping the target's turns its phase; a background in pairs removes
    it before the phase is read (an amplitude background cannot)."""
    pipe = build_pipeline(quad)
    pairs, _, _ = _scene_frame(quad, TARGETS[0], seed=5, noise=0.0)
    rng = np.random.default_rng(1)
    static = np.zeros_like(pairs)
    t = np.arange(128)
    for c in range(4):  # a static echo on each target echo's tail, another phase
        peak = np.hypot(pairs[c, 0::2], pairs[c, 1::2])
        toa = np.argmax(peak) + 2.5
        amp = 0.3 * peak.max() * np.exp(-0.5 * ((t - toa) / 1.2) ** 2)
        phi = rng.uniform(0, 2 * math.pi)
        static[c, 0::2], static[c, 1::2] = amp * math.sin(phi), amp * math.cos(phi)
    mixed = pairs + static
    with_pairs = pipe.process(mixed, static)
    assert with_pairs.record()["timing"] == "iq"
    assert np.linalg.norm(with_pairs.position_mm - TARGETS[0]) < 0.05
    amplitude_bg = pipe.process(mixed, np.hypot(static[:, 0::2], static[:, 1::2]))
    assert np.linalg.norm(amplitude_bg.position_mm - TARGETS[0]) > 0.05


def test_a_short_wrap_is_warned_about(caplog):
    """At 22 kHz a 175 kHz carrier wraps every 0.126 sample, under twice the envelope's error:
    the phase cannot be trusted to pick its wrap, and the log says so (the default timing of
    an I/Q profile is the envelope, which is not warned about)."""
    icra = load_profile("spiel-icra23")
    with caplog.at_level("WARNING", logger="spiel_edge.pipeline.iq3d"):
        build_pipeline(_with(icra, acquisition={"signal": "iq"}))
        assert not caplog.records
        build_pipeline(_with(icra, acquisition={"signal": "iq"}, ranging={"timing": "iq"}))
    assert "wraps every 0.126 samples" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="spiel_edge.pipeline.iq3d"):
        build_pipeline(load_profile("ch101-quad-iq"))
    assert not caplog.records
