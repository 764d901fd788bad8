"""numba kernels for spiel_edge.protocol.cobs (imported only when numba is available).

Error codes as in spiel_edge.protocol.cobs: -2 a code past the end (the caller rejects zero bytes);
``decode_pieces`` adds -3 (a piece over its size limit) and -4 (an empty piece).
"""

from __future__ import annotations

import numpy as np

try:  # spiel_edge's kernel cache: prebuilt kernels, and a bad cache file never a crash
    from spiel_edge._jit import jit
except ImportError:  # pragma: no cover - the codec without spiel_edge's numba layer
    from numba import njit

    def jit(fn=None, **extra):
        """``@jit`` or ``@jit(inline=...)``, as spiel_edge._jit.jit takes them."""
        options = {"cache": True, "nogil": True, **extra}
        return njit(**options) if fn is None else njit(**options)(fn)


@jit(inline="always")
def _decode_span(src, pos, end, dst, out):  # pragma: no cover - compiled
    # src[pos:end] holds no zero byte; decoded into dst from ``out``: its size, or -2
    first = out
    while pos < end:
        code = np.int64(src[pos])
        stop = pos + code
        if stop > end:
            return -2
        if code > 32:  # a slice copy pays off on long blocks, a plain loop on short ones
            dst[out : out + code - 1] = src[pos + 1 : stop]
            out += code - 1
        else:
            for i in range(pos + 1, stop):
                dst[out] = src[i]
                out += 1
        if code != 0xFF and stop < end:
            dst[out] = 0
            out += 1
        pos = stop
    return out - first


@jit
def decode(src, dst):  # pragma: no cover - compiled
    # the caller has checked that src holds no zero byte (a C-speed scan)
    return _decode_span(src, 0, src.shape[0], dst, 0)


@jit
def decode_pieces(src, dst, starts, sizes, max_piece):  # pragma: no cover - compiled
    # every zero byte of src ends a piece; piece k decodes into dst at starts[k] (its own
    # offset in src: a decoded piece is never longer). sizes[k]: the decoded size, or -2 (a
    # code past the piece's end), -3 (longer than max_piece), -4 (empty)
    n = 0
    begin = 0
    for pos in range(src.shape[0]):
        if src[pos] != 0:
            continue
        starts[n] = begin
        if pos == begin:
            sizes[n] = -4
        elif pos - begin > max_piece:
            sizes[n] = -3
        else:
            sizes[n] = _decode_span(src, begin, pos, dst, begin)
        n += 1
        begin = pos + 1
    return n


@jit
def encode(src, dst):  # pragma: no cover - compiled
    # dst holds len(src) + len(src) // 254 + 1 bytes: the worst case
    size = src.shape[0]
    code_at = 0
    out = 1
    run = 0
    for i in range(size):
        byte = src[i]
        if byte == 0:
            dst[code_at] = run + 1
            code_at = out
            out += 1
            run = 0
        else:
            dst[out] = byte
            out += 1
            run += 1
            if run == 254:
                dst[code_at] = 0xFF
                run = 0
                if i + 1 < size:  # a block ending the data needs no further code
                    code_at = out
                    out += 1
                else:
                    return out
    dst[code_at] = run + 1
    return out
