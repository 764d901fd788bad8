"""Dump every front-kernel output and fused Result for a fixed input set, or compare two dumps
bit for bit (docs/history/front-speed.md).

    python tools/research/front_identity.py real REAL.npz [FOLDER]   # spiel-icra23 train_val + _bg
    python tools/research/front_identity.py dump OUT.pkl [REAL.npz]
    python tools/research/front_identity.py compare A.pkl B.pkl

Inputs: the vendored 4 x 64 subset, the real acquisitions of REAL.npz (with their background,
without one, and with [memg] split_merged on), bench's synthetic 8 x 256 and 16 x 1024 sets,
and an RF variant of the 8 x 256 set (the envelope kernel). Comparison is on the bytes of
every array (so -0.0 vs 0.0 or a different NaN payload counts as a difference).
"""

from __future__ import annotations

import dataclasses
import pickle
import sys

import numpy as np

from spiel_edge.data import load_subset
from spiel_edge.measure.bench import synthetic_set
from spiel_edge.pipeline.compiled import abi
from spiel_edge.pipeline.compiled.front import packed_front
from spiel_edge.pipeline.compiled.fused import FusedPipeline, as_float64
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.profile.schema import load_profile


def _front(fused: FusedPipeline, f, b) -> tuple:
    p = fused.pipeline
    if not fused.profile.preprocess.background_subtraction:
        b = None
    elif b is None:
        b = p.static_model
    ws = fused._workspaces.get()
    y = as_float64(f, "frames")
    bg = as_float64(b, "background") if b is not None else ws.background[:0]
    settings = abi.front_constants(fused.profile)
    fi = np.array([int(settings[n]) for n in abi.FRONT_INTS], dtype=np.int64)
    ff = np.array([settings[n] for n in abi.FRONT_FLOATS], dtype=np.float64)
    features, counts = np.empty_like(ws.features), np.empty_like(ws.counts)
    status = packed_front(y, bg, fi, ff, *ws.front_buffers, features, counts)
    bufs = ws.front_buffers[2:]  # cleaned .. features (envelopes hold garbage unless rf)
    return (status,) + tuple(a.tobytes() for a in bufs)


def _result(r) -> tuple:
    pos = None if r.position_mm is None else np.asarray(r.position_mm).tobytes()
    return (
        r.reason,
        r.matched,
        r.echoes,
        pos,
        repr(r.residual_mm),
        np.asarray(r.features).tobytes(),
        np.asarray(r.counts).tobytes(),
        repr([t.record() for t in r.targets]),
    )


def _run(name, prof, frames, backgrounds, out):
    fused = FusedPipeline(Pipeline(prof))
    rows = []
    for i, f in enumerate(frames):
        b = None if backgrounds is None else backgrounds[i]
        rows.append((_front(fused, f, b), _result(fused.process(f, b))))
    out[name] = rows
    print(name, len(rows), flush=True)


def dump(path: str, real: str | None) -> None:
    out: dict = {}
    profile = load_profile()
    split = profile.replace(
        memg=dataclasses.replace(profile.memg, split_merged=True, split_min_sigma=2.0)
    )
    sub = load_subset()
    _run("subset_bg", profile, sub.frames, sub.backgrounds, out)
    if real:
        with np.load(real) as d:
            fr, bg = d["frames"].astype(np.float64), d["backgrounds"].astype(np.float64)
        _run("real_bg", profile, fr, bg, out)
        _run("real_nobg", profile, fr, None, out)
        _run("real_split_bg", split, fr, bg, out)
        _run("real_split_nobg", split, fr, None, out)
    for n_ch, n_t, count in ((8, 256, 100), (16, 1024, 30)):
        prof, frames, backgrounds = synthetic_set(n_ch, n_t, count)
        _run(f"syn_{n_ch}x{n_t}", prof, frames, backgrounds, out)
        sp = prof.replace(memg=dataclasses.replace(prof.memg, split_merged=True))
        _run(f"syn_split_{n_ch}x{n_t}", sp, frames, backgrounds, out)
    prof, frames, backgrounds = synthetic_set(8, 256, 20, seed=7)
    rf = prof.replace(
        acquisition=dataclasses.replace(prof.acquisition, signal="rf", carrier_hz=5000.0)
    )
    carrier = np.sin(np.arange(256) * 2 * np.pi * 5000 / prof.acquisition.sample_rate_hz)
    _run("syn_rf_8x256", rf, frames * carrier, backgrounds * carrier, out)
    with open(path, "wb") as fh:
        pickle.dump(out, fh)


def real(path: str, folder: str = "/work/shared/datasets/spiel-icra23") -> None:
    """Every train_val recording with its train_val_bg background, as arrays."""
    from spiel_edge.recordings.spiel_csv import frame_files, read_recording

    frames, backgrounds = [], []
    for p in frame_files(f"{folder}/train_val"):
        rec = read_recording(p, f"{folder}/train_val_bg")
        if rec.error is not None:
            raise SystemExit(rec.error)
        frames.append(rec.frames)
        backgrounds.append(rec.background)
    np.savez(path, frames=np.array(frames), backgrounds=np.array(backgrounds))
    print(len(frames), "acquisitions")


def compare(a_path: str, b_path: str) -> int:
    with open(a_path, "rb") as fh:
        a = pickle.load(fh)
    with open(b_path, "rb") as fh:
        b = pickle.load(fh)
    bad = 0
    assert a.keys() == b.keys(), (a.keys(), b.keys())
    for name in a:
        diff = [i for i, (x, y) in enumerate(zip(a[name], b[name], strict=True)) if x != y]
        print(f"{name}: {len(a[name])} acquisitions, {len(diff)} differ {diff[:5]}")
        bad += len(diff)
    print("IDENTICAL" if bad == 0 else f"{bad} DIFFER")
    return 1 if bad else 0


if __name__ == "__main__":
    if sys.argv[1] == "real":
        real(*sys.argv[2:])
    elif sys.argv[1] == "dump":
        dump(sys.argv[2], sys.argv[3] if len(sys.argv) > 3 else None)
    else:
        sys.exit(compare(sys.argv[2], sys.argv[3]))
