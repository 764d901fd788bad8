"""The message base class: frozen dataclass fields <-> one precompiled ``struct.Struct``.

Forward-compatibility rule (PROTOCOL.md "Versioning"): payloads only grow at the end. A
receiver zero-fills a payload shorter than the fixed part and ignores bytes after what it
knows. A message with a variable-length tail keeps the tail's byte length (u16) as the last
item of its fixed part; the tail follows the fixed part, and later fields go after the tail.
"""

from __future__ import annotations

import re
import struct
from dataclasses import astuple
from typing import Any, ClassVar, TypeVar

from spiel_edge.protocol.errors import MessageError

__all__ = ["REGISTRY", "Message", "item_codes", "register"]

M = TypeVar("M", bound="Message")
C = TypeVar("C", bound="type[Message]")
_ITEM = re.compile(r"(\d*)([a-zA-Z?])")


def item_codes(fmt: str) -> list[str]:
    """One code per struct item (``"<BH16s"`` -> ``["B", "H", "16s"]``), pad bytes skipped."""
    codes = []
    for count, code in _ITEM.findall(fmt):
        if code == "x":
            continue
        codes.extend([count + code] if code == "s" else [code] * int(count or 1))
    return codes


class Message:
    """Base of every message; subclasses are frozen dataclasses.

    ``_STRUCT`` lists the dataclass fields in order (the tail field excluded, its length
    included as the last item). ``s`` items are ``str`` fields, UTF-8 and NUL-padded.
    """

    MSG_TYPE: ClassVar[int] = -1
    RESPONSE: ClassVar[bool] = False
    TIMEOUT_S: ClassVar[float] = 0.5  # response timeout of a request (see PROTOCOL.md)
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<")
    _TAIL: ClassVar[str] = ""  # name of the variable-length last field ("" = none)
    _TAIL_IS_TEXT: ClassVar[bool] = False
    _CODES: ClassVar[list[str]] = []

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls._CODES = item_codes(cls._STRUCT.format)

    def pack(self) -> bytes:
        values = list(astuple(self))  # type: ignore[call-overload]
        tail = b""
        if self._TAIL:
            tail = _to_bytes(values.pop(), None, self._TAIL)
            values.append(len(tail))
        for i, code in enumerate(self._CODES):
            if code.endswith("s"):
                values[i] = _to_bytes(values[i], int(code[:-1] or 1), f"field {i}")
        try:
            return self._STRUCT.pack(*values) + tail
        except struct.error as exc:
            raise MessageError(f"{type(self).__name__}: {exc}") from exc

    @classmethod
    def unpack(cls: type[M], payload: bytes) -> M:
        size = cls._STRUCT.size
        head = bytes(payload[:size]).ljust(size, b"\x00")  # zero-fill short payloads
        values: list[Any] = list(cls._STRUCT.unpack(head))
        for i, code in enumerate(cls._CODES):
            if code.endswith("s"):
                values[i] = values[i].rstrip(b"\x00").decode("utf-8", "replace")
        if cls._TAIL:
            n = values.pop()
            tail = bytes(payload[size : size + n])
            if len(tail) != n:
                raise MessageError(f"{cls.__name__}: tail of {n} bytes truncated to {len(tail)}")
            values.append(tail.decode("utf-8", "replace") if cls._TAIL_IS_TEXT else tail)
        return cls(*values)


def _to_bytes(value: Any, limit: int | None, name: str) -> bytes:
    if isinstance(value, str):
        if "\x00" in value:
            raise MessageError(f"{name}: text must not contain NUL")
        value = value.encode("utf-8")
    data = bytes(value)
    if limit is not None and len(data) > limit:
        raise MessageError(f"{name}: {len(data)} bytes is too long")
    return data


REGISTRY: dict[tuple[int, bool], type[Message]] = {}


def register(cls: C) -> C:
    """Add a message class to REGISTRY under (MSG_TYPE, RESPONSE)."""
    key = (cls.MSG_TYPE, cls.RESPONSE)
    if key in REGISTRY:
        raise RuntimeError(f"duplicate message key {key}")
    REGISTRY[key] = cls
    return cls
