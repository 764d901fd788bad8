"""Every input bounded before it is read, in one place (issue 28, part 2): a size limit per kind
of file, .npy headers checked before their data, .npz members' uncompressed sizes checked
before anything is decompressed, FIFOs and devices refused. Size bombs are sparse files or
small zips: each case costs well under a megabyte and a second."""

from __future__ import annotations

import io
import os
import time
import tracemalloc
import zipfile

import numpy as np
import pytest

from spiel_edge.errors import SpielError
from spiel_edge.runtime.loop import load_background
from spiel_edge.safety import limits

GIB = 1 << 30


def _npy_header(descr: str, shape: tuple, fortran: bool = False, version=(1, 0)) -> bytes:
    text = f"{{'descr': '{descr}', 'fortran_order': {fortran}, 'shape': {shape}, }}"
    prefix = b"\x93NUMPY" + bytes(version)
    size_bytes = 2 if version == (1, 0) else 4
    total = len(prefix) + size_bytes + len(text) + 1
    pad = (-total) % 64
    body = (text + " " * pad + "\n").encode("latin1")
    return prefix + len(body).to_bytes(size_bytes, "little") + body


def _sparse(path, header: bytes, size: int):
    with open(path, "wb") as fh:
        fh.write(header)
        fh.truncate(size)
    return path


def _bounded(fn, *args, max_s: float = 5.0, max_bytes: int = 4 << 20):
    """Run ``fn``; it must raise a SpielError quickly and with little memory. The error."""
    tracemalloc.start()
    t0 = time.monotonic()
    try:
        with pytest.raises(SpielError) as info:
            fn(*args)
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert time.monotonic() - t0 < max_s
    assert peak < max_bytes, f"{peak} bytes allocated"
    message = str(info.value)
    assert "\n" not in message
    return message


# --- .npy backgrounds: the header first -------------------------------------------------------


def _bad_npys(tmp_path):
    """name -> (path, needle of the message)."""
    d = tmp_path
    cases = {}

    def save(name, arr):
        np.save(d / name, arr, allow_pickle=True)
        return d / name

    cases["sparse-2.5GB"] = (
        _sparse(d / "big.npy", _npy_header("<f8", (4, 80_000_000)), int(2.5 * GIB)),
        "more than",
    )
    cases["header-claims-2GB"] = (
        _sparse(d / "claims.npy", _npy_header("<f8", (4, 67_108_864)), 4096),
        "more than it may hold",
    )
    cases["shape-overflows"] = (
        _sparse(d / "ovf.npy", _npy_header("<f8", (2**40, 2**40)), 4096),
        "more than it may hold",
    )
    cases["strings"] = (save("str.npy", np.array(["a", "b"])), "not numbers")
    cases["bytes"] = (save("bytes.npy", np.array([b"a", b"b"])), "not numbers")
    cases["structured"] = (
        save("rec.npy", np.zeros(3, dtype=[("a", "f4"), ("b", "i4")])),
        "not numbers",
    )
    cases["objects-pickled"] = (
        save("obj.npy", np.array([{"a": 1}, None], dtype=object)),
        "not numbers",
    )
    cases["datetimes"] = (save("dt.npy", np.zeros(3, dtype="M8[s]")), "not numbers")
    cases["complex"] = (save("cplx.npy", np.zeros((4, 8), dtype=complex)), "not numbers")
    (d / "magic.npy").write_bytes(b"NOTNUMPY" + bytes(200))
    cases["bad-magic"] = (d / "magic.npy", "not a .npy")
    (d / "empty.npy").write_bytes(b"")
    cases["empty"] = (d / "empty.npy", "not a .npy")
    (d / "cut.npy").write_bytes(_npy_header("<f8", (4, 64))[:20])
    cases["cut-header"] = (d / "cut.npy", "not a .npy")
    (d / "short.npy").write_bytes(_npy_header("<f8", (4, 64)) + bytes(100))
    cases["cut-data"] = (d / "short.npy", "cut short")
    (d / "v9.npy").write_bytes(b"\x93NUMPY\x09\x00" + bytes(100))
    cases["version-9"] = (d / "v9.npy", "not a .npy")
    (d / "code.npy").write_bytes(
        _npy_header("<f8", (4, 64)).replace(b"'descr': '<f8'", b"'descr': __import__('os')")
    )
    cases["code-in-header"] = (d / "code.npy", "not a .npy")
    cases["nan"] = (save("nan.npy", np.full((4, 64), np.nan)), "finite")
    cases["inf"] = (save("inf.npy", np.full((4, 64), np.inf)), "finite")
    cases["1-d"] = (save("flat.npy", np.zeros(256)), "(channels, samples)")
    cases["3-d"] = (save("cube.npy", np.zeros((2, 4, 64))), "(channels, samples)")
    cases["scalar"] = (save("scalar.npy", np.float64(3.0)), "(channels, samples)")
    fifo = d / "fifo.npy"
    os.mkfifo(fifo)
    cases["fifo"] = (fifo, "not a regular file")
    cases["folder"] = ((d / "folder.npy"), "not a regular file")
    (d / "folder.npy").mkdir()
    (d / "loop.npy").symlink_to(d / "loop.npy")
    cases["symlink-loop"] = (d / "loop.npy", "cannot read")
    cases["missing"] = (d / "none.npy", "not found")
    return cases


NPY_CASES = [
    "sparse-2.5GB",
    "header-claims-2GB",
    "shape-overflows",
    "strings",
    "bytes",
    "structured",
    "objects-pickled",
    "datetimes",
    "complex",
    "bad-magic",
    "empty",
    "cut-header",
    "cut-data",
    "version-9",
    "code-in-header",
    "nan",
    "inf",
    "1-d",
    "3-d",
    "scalar",
    "fifo",
    "folder",
    "symlink-loop",
    "missing",
]


@pytest.mark.parametrize("case", NPY_CASES)
def test_hostile_npy_backgrounds_are_refused_unread(tmp_path, case):
    path, needle = _bad_npys(tmp_path)[case]
    message = _bounded(load_background, path)
    assert needle in message, message


def test_a_fortran_order_background_is_read_right(tmp_path):
    arr = np.asfortranarray(np.arange(256, dtype=np.float32).reshape(4, 64))
    np.save(tmp_path / "f.npy", arr)
    assert np.array_equal(load_background(tmp_path / "f.npy"), arr)


def test_a_version_2_header_is_read(tmp_path):
    arr = np.arange(256, dtype="<u2").reshape(4, 64)
    path = tmp_path / "v2.npy"
    path.write_bytes(_npy_header("<u2", (4, 64), version=(2, 0)) + arr.tobytes())
    assert np.array_equal(load_background(path), arr)


@pytest.mark.parametrize("case", ["sparse-2.5GB", "strings", "structured", "fifo"])
def test_run_refuses_a_hostile_background_before_the_board(cli, tmp_path, case):
    path, needle = _bad_npys(tmp_path)[case]
    ran = cli("run", "--port", "serial:///nonexistent/tty", "--background", path)
    assert ran.status == 2 and (needle in ran.err or "regular" in ran.err), ran


# --- .npz archives: sizes before decompression ------------------------------------------------


def _npz(path, members: dict[str, bytes], compression=zipfile.ZIP_DEFLATED):
    with zipfile.ZipFile(path, "w", compression) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


def _npy_bytes(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=True)
    return buf.getvalue()


def _zip_bomb(path, mib: int = 80):
    """A real bomb: a deflated member of ``mib`` MiB of zeros, a few hundred kB on disk."""
    with (
        zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf,
        zf.open("median.npy", "w", force_zip64=True) as member,
    ):
        member.write(_npy_header("<f8", (mib * 131072,)))
        zero = bytes(1 << 20)
        for _ in range(mib):
            member.write(zero)
    return path


GOOD = {"median": np.zeros((4, 64)), "mad": np.ones((4, 64))}


def _bad_npzs(tmp_path):
    d = tmp_path
    ok = {f"{k}.npy": _npy_bytes(v) for k, v in GOOD.items()}
    cases = {
        "zip-bomb": (_zip_bomb(d / "bomb.npz"), "once decompressed"),
        "sparse": (_sparse(d / "sparse.npz", b"PK\x03\x04", 2 * GIB), "more than"),
        "many-members": (
            _npz(d / "many.npz", {f"m{i}.npy": _npy_bytes(np.zeros(1)) for i in range(100)}),
            "members",
        ),
        "not-npy-member": (_npz(d / "txt.npz", {**ok, "readme.txt": b"hi"}), "not a .npy"),
        "pickled-member": (
            _npz(d / "pickle.npz", {**ok, "x.npy": _npy_bytes(np.array([None], dtype=object))}),
            "not numbers",
        ),
        "string-member": (
            _npz(d / "str.npz", {**ok, "median.npy": _npy_bytes(np.array(["a"]))}),
            "not numbers",
        ),
        "header-lies": (
            _npz(d / "lies.npz", {**ok, "median.npy": _npy_header("<f8", (2**31, 64))}),
            "more than it may hold",
        ),
        "not-a-zip": (d / "plain.npz", "not a .npz"),
        "a-npy": (d / "model.npy", "not a .npz"),
        "truncated": (d / "cut.npz", "not a .npz"),
        "damaged-member": (d / "damaged.npz", "damaged|not a .npy"),
        "empty": (d / "empty.npz", "not a .npz"),
        "fifo": (d / "fifo.npz", "not a regular file"),
        "no-median": (_npz(d / "nomedian.npz", {"mad.npy": ok["mad.npy"]}), "no median"),
    }
    (d / "plain.npz").write_text("median,mad\n")
    np.save(d / "model.npy", np.zeros((4, 64)))
    full = _npz(d / "full.npz", ok).read_bytes()
    (d / "cut.npz").write_bytes(full[: len(full) // 2])
    damaged = bytearray(_npz(d / "d.npz", ok, zipfile.ZIP_DEFLATED).read_bytes())
    damaged[60:90] = bytes(30)
    (d / "damaged.npz").write_bytes(bytes(damaged))
    (d / "empty.npz").write_bytes(b"")
    os.mkfifo(d / "fifo.npz")
    return cases


@pytest.fixture(scope="module")
def npzs(tmp_path_factory):
    return _bad_npzs(tmp_path_factory.mktemp("npz"))


NPZ_CASES = [
    "zip-bomb",
    "sparse",
    "many-members",
    "not-npy-member",
    "pickled-member",
    "string-member",
    "header-lies",
    "not-a-zip",
    "a-npy",
    "truncated",
    "damaged-member",
    "empty",
    "fifo",
    "no-median",
]


def _profile_with_static_model(tmp_path, model) -> str:
    from spiel_edge.profile.schema import dump_toml, load_profile, profile_to_dict

    data = profile_to_dict(load_profile("spiel-icra23"))
    data["scene"]["static_model"] = str(model)
    path = tmp_path / "with_model.toml"
    path.write_text(dump_toml(data))
    return str(path)


@pytest.mark.parametrize("case", NPZ_CASES)
def test_hostile_static_models_are_refused_at_profile_load(tmp_path, npzs, case):
    import re

    from spiel_edge.profile.schema import load_profile

    model, needle = npzs[case]
    profile = _profile_with_static_model(tmp_path, model)
    message = _bounded(load_profile, profile, max_bytes=8 << 20)
    assert "scene.static_model" in message and re.search(needle, message), message


def test_a_good_static_model_loads(tmp_path):
    from spiel_edge.profile.schema import load_profile

    model = _npz(tmp_path / "ok.npz", {f"{k}.npy": _npy_bytes(v) for k, v in GOOD.items()})
    assert load_profile(_profile_with_static_model(tmp_path, model)).scene.static_model


@pytest.fixture(scope="module")
def big_bomb(tmp_path_factory):
    """300 MiB of zeros in about 300 kB: beyond the scenes' bound (256 MiB)."""
    return _zip_bomb(tmp_path_factory.mktemp("bomb") / "scenes.npz", mib=300)


@pytest.mark.parametrize("case", ["zip-bomb", "many-members", "pickled-member", "a-npy"])
def test_hostile_scene_files_are_refused(npzs, big_bomb, case):
    from spiel_edge.measure.scenes import load_scenes

    path, needle = npzs[case]
    if case == "zip-bomb":  # the scenes' bound is larger (256 MiB): a larger bomb
        path = big_bomb
    message = _bounded(load_scenes, path, max_bytes=8 << 20)
    assert needle in message or "not a scene" in message, message


def test_evaluate_a_npy_is_one_line(cli, tmp_path):
    np.save(tmp_path / "x.npy", np.zeros((4, 64)))
    ran = cli("evaluate", tmp_path / "x.npy")
    assert ran.status == 2 and len(ran.err.strip().splitlines()) == 1, ran


def test_evaluate_a_zip_bomb_is_refused_unread(cli, big_bomb):
    ran = cli("evaluate", big_bomb)
    assert ran.status == 2 and "once decompressed" in ran.err, ran


# --- text inputs: a limit per kind ----------------------------------------------------------

TEXT_KINDS = ["profile", "calibration", "config", "positions", "env", "labels"]


def _hostile_text(tmp_path, how: str):
    path = tmp_path / f"in_{how}.txt"
    if how == "sparse-2GB":
        _sparse(path, b"a = 1\n", 2 * GIB)
    elif how == "fifo":
        os.mkfifo(path)
    elif how == "device":
        return "/dev/zero"
    elif how == "binary":
        path.write_bytes(b"\xff\xfe\x00\x80garbage")
    return path


@pytest.mark.parametrize("how", ["sparse-2GB", "fifo", "device", "binary"])
@pytest.mark.parametrize("kind", TEXT_KINDS)
def test_text_inputs_bounded_and_regular(tmp_path, kind, how):
    path = _hostile_text(tmp_path, how)
    message = _bounded(limits.read_input_text, path, kind)
    assert kind in message


def test_calibrate_positions_2gb_refused_unread(cli, tmp_path):
    path = _hostile_text(tmp_path, "sparse-2GB")
    t0 = time.monotonic()
    ran = cli("calibrate", "--positions", path, "--port", "sim://?scene=model", "--no-prompt")
    assert ran.status == 2 and "positions" in ran.err and "more than" in ran.err, ran
    assert time.monotonic() - t0 < 30


def test_doctor_does_not_read_a_2gb_env_file(cli, tmp_path):
    _sparse(tmp_path / "spiel-edge.env", b"SPIEL_PORT=sim://\n", 2 * GIB)
    ran = cli("doctor", "--config", tmp_path, "--skip-numba")
    assert ran.status in (0, 1), ran
    assert "env" in ran.out + ran.err and "more than" in ran.out + ran.err


def test_empty_labels_file_gives_no_library_warning(tmp_path, recwarn):
    from spiel_edge.recordings.spiel_csv import read_truth

    (tmp_path / "x_frames.csv").write_text("1,2\n")
    (tmp_path / "x_labels.csv").write_text("")
    assert read_truth(tmp_path / "x_frames.csv") is None
    assert not recwarn.list


def test_labels_that_are_a_fifo_do_not_block(tmp_path):
    from spiel_edge.recordings.spiel_csv import read_truth

    (tmp_path / "x_frames.csv").write_text("1,2\n")
    os.mkfifo(tmp_path / "x_labels.csv")
    t0 = time.monotonic()
    assert read_truth(tmp_path / "x_frames.csv") is None
    assert time.monotonic() - t0 < 1


@pytest.mark.parametrize(
    ("toml", "where"),
    [
        ("a = " + "[" * 5000 + "]" * 5000, "list"),
        ("a = " + "{b = " * 3000 + "1" + "}" * 3000, "inline-table"),
        ("[" + ".".join(["t"] * 5000) + "]", "dotted-table"),
    ],
    ids=lambda v: v if len(v) < 20 else "",
)
@pytest.mark.parametrize("option", ["--profile", "--calibration", "config"])
def test_deeply_nested_toml_is_one_line(cli, tmp_path, csv_folder, toml, where, option):
    path = tmp_path / "deep.toml"
    path.write_text(toml)
    if option == "config":
        ran = cli("config", "push", path, "--port", "serial:///nonexistent/tty")
    else:
        ran = cli("replay", csv_folder[0], option, path, "-o", tmp_path / "o.ndjson")
    assert ran.status == 2 and len(ran.err.strip().splitlines()) == 1, ran
    assert not (tmp_path / "o.ndjson").exists()
