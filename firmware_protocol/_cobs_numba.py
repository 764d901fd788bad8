"""numba kernels for firmware_protocol.cobs (imported only when numba is available).

Error code as in firmware_protocol.cobs: -2 a code past the end (the caller rejects zero bytes).
"""

from __future__ import annotations

import numpy as np

try:  # spiel_edge's kernel cache: prebuilt kernels, and a bad cache file never a crash
    from spiel_edge._jit import jit
except ImportError:  # pragma: no cover - firmware_protocol copied without spiel_edge
    from numba import njit

    jit = njit(cache=True, nogil=True)


@jit
def decode(src, dst):  # pragma: no cover - compiled
    # the caller has checked that src holds no zero byte (a C-speed scan)
    size = src.shape[0]
    pos = 0
    out = 0
    while pos < size:
        code = np.int64(src[pos])
        end = pos + code
        if end > size:
            return -2
        if code > 32:  # a slice copy pays off on long blocks, a plain loop on short ones
            dst[out : out + code - 1] = src[pos + 1 : end]
            out += code - 1
        else:
            for i in range(pos + 1, end):
                dst[out] = src[i]
                out += 1
        if code != 0xFF and end < size:
            dst[out] = 0
            out += 1
        pos = end
    return out


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
