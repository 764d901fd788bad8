"""spiel_edge.protocol.cobs (numba kernels and pure fallback) against a per-byte reference."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spiel_edge.protocol import cobs


def reference_encode(data: bytes) -> bytes:
    """COBS as in the paper, written per byte (the ``cobs`` package's output)."""
    out = bytearray(b"\x00")
    code_at, run = 0, 0
    for index, byte in enumerate(data):
        if byte == 0:
            out[code_at] = run + 1
            code_at, run = len(out), 0
            out.append(0)
            continue
        out.append(byte)
        run += 1
        if run == 254:
            out[code_at] = 0xFF
            run = 0
            if index + 1 < len(data):
                code_at = len(out)
                out.append(0)
            else:
                return bytes(out)
    out[code_at] = run + 1
    return bytes(out)


def reference_decode(data: bytes) -> bytes | None:
    out = bytearray()
    pos = 0
    while pos < len(data):
        code = data[pos]
        if code == 0 or pos + code > len(data):
            return None
        block = data[pos + 1 : pos + code]
        if 0 in block:
            return None
        out += block
        if code != 0xFF and pos + code < len(data):
            out.append(0)
        pos += code
    return bytes(out)


cobs.warm_up()  # cobs.encode/decode below are the numba kernels, *_pure the fallback
ENCODERS = [cobs.encode, cobs.encode_pure]
DECODERS = [cobs.decode, cobs.decode_pure]
EDGES = [b"", b"\x00", b"\x00\x00", b"\x01" * 253, b"\x01" * 254, b"\x01" * 255]
EDGES += [b"\x01" * 254 + b"\x00", b"\x01" * 508, b"\x00" + b"\x02" * 300 + b"\x00"]


def test_numba_kernels_are_used() -> None:
    assert cobs.kernels() is not None


@pytest.mark.parametrize("data", EDGES)
def test_edges_match_the_reference(data: bytes) -> None:
    for encode, decode in zip(ENCODERS, DECODERS, strict=True):
        assert encode(data) == reference_encode(data)
        assert decode(reference_encode(data)) == data


# zero-heavy and zero-free data both: zeros start blocks, long runs hit the 254-byte limit
payloads = st.one_of(
    st.binary(max_size=1200),
    st.lists(st.sampled_from([0, 1, 255]), max_size=800).map(bytes),
    st.integers(0, 800).map(lambda n: b"\x07" * n),
)


@settings(max_examples=300, deadline=None)
@given(payloads)
def test_round_trip_matches_the_reference(data: bytes) -> None:
    expected = reference_encode(data)
    assert 0 not in expected
    for encode, decode in zip(ENCODERS, DECODERS, strict=True):
        assert encode(data) == expected
        assert decode(expected) == data


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=40))
def test_invalid_input_is_rejected_like_the_reference(data: bytes) -> None:
    expected = reference_decode(data)
    for decode in DECODERS:
        if expected is None:
            with pytest.raises(cobs.CobsDecodeError):
                decode(data)
        else:
            assert decode(data) == expected


def test_accepts_bytearray_and_memoryview() -> None:
    wire = cobs.encode(b"ab\x00cd")
    assert cobs.decode(bytearray(wire)) == cobs.decode(memoryview(wire)) == b"ab\x00cd"
    assert cobs.encode(memoryview(b"ab\x00cd")) == wire


def test_cobs_kernels_load_without_spiel_edge(tmp_path):
    """firmware_protocol copied without spiel_edge: the plain-numba fallback decorates every
    kernel (it once raised TypeError at import) and decodes like the reference."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(
        """
        import sys
        sys.modules["spiel_edge._jit"] = None  # import of it raises ImportError
        from spiel_edge.protocol import _cobs_numba as k
        from spiel_edge.protocol import cobs
        import numpy as np
        data = bytes(range(1, 40)) + b"\\0" + bytes(300)
        enc = cobs.encode(data)
        out = np.zeros(len(data) + 8, np.uint8)
        n = k.decode(np.frombuffer(enc, np.uint8), out)
        assert bytes(out[:n]) == data, (n, len(data))
        print("ok")
        """
    )
    env = {"NUMBA_CACHE_DIR": str(tmp_path), "PATH": "/usr/bin:/bin"}
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "ok"
