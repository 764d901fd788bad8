"""Hypothesis strategies for every registered message, derived from its struct layout."""

from __future__ import annotations

import dataclasses

from hypothesis import strategies as st

from spiel_edge.protocol import MAX_PAYLOAD, REGISTRY, SAMPLE_SIZE, SampleFormat, StreamData
from spiel_edge.protocol._codec import Message

_INT_BITS = {
    "B": (8, False),
    "H": (16, False),
    "I": (32, False),
    "Q": (64, False),
    "b": (8, True),
    "h": (16, True),
    "i": (32, True),
    "q": (64, True),
}


def _int(code: str) -> st.SearchStrategy[int]:
    bits, signed = _INT_BITS[code]
    if signed:
        return st.integers(-(1 << (bits - 1)), (1 << (bits - 1)) - 1)
    return st.integers(0, (1 << bits) - 1)


def _text(max_bytes: int) -> st.SearchStrategy[str]:
    chars = st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00")
    return st.text(chars, max_size=max_bytes).filter(lambda s: len(s.encode()) <= max_bytes)


def _field(code: str) -> st.SearchStrategy:
    if code.endswith("s"):
        return _text(int(code[:-1] or 1))
    if code == "f":
        return st.floats(width=32, allow_nan=False)
    return _int(code)


def stream_data(max_samples: int | None = None) -> st.SearchStrategy[StreamData]:
    @st.composite
    def build(draw: st.DrawFn) -> StreamData:
        fmt = draw(st.sampled_from(list(SampleFormat)))
        size = SAMPLE_SIZE[fmt]
        limit = (MAX_PAYLOAD - 24) // size if max_samples is None else max_samples
        n = draw(st.integers(0, limit))
        n_ch = draw(st.integers(1, 255))
        return StreamData(
            draw(_int("I")),
            draw(st.integers(0, n_ch - 1)),
            n_ch,
            fmt,
            draw(_int("I")),
            draw(_int("Q")),
            draw(st.binary(min_size=n * size, max_size=n * size)),
        )

    return build()


def message_of(cls: type[Message], max_tail: int | None = None) -> st.SearchStrategy[Message]:
    if cls is StreamData:
        return stream_data(None if max_tail is None else max_tail // 4)
    codes = list(cls._CODES)
    tail: list[st.SearchStrategy] = []
    if cls._TAIL:
        codes.pop()  # the tail's length item is computed by pack()
        room = MAX_PAYLOAD - cls._STRUCT.size if max_tail is None else max_tail
        tail = [_text(room) if cls._TAIL_IS_TEXT else st.binary(max_size=room)]
    assert len(codes) + len(tail) == len(dataclasses.fields(cls))  # type: ignore[arg-type]
    return st.builds(cls, *[_field(c) for c in codes], *tail)


def any_message(max_tail: int | None = 64) -> st.SearchStrategy[Message]:
    return st.one_of([message_of(cls, max_tail) for cls in REGISTRY.values()])
