"""How the numba kernels take many arrays in few arguments: a declared table.

numba's dispatch costs about 65 ns per array argument, so the compiled path and the tracker
hand their kernels a few flat buffers, one per dtype, and the kernels read views of them. What
lies where is declared once, as a :class:`Table` of :class:`Field` (name, dtype, dimensions),
and everything else follows from it: each field's buffer (by its dtype) and offset, the
packing of a pipeline's constants (:meth:`Table.pack`) and the slot numbers the kernels' view
functions read (:meth:`Table.slots`). Tests check the kernels' view functions and parameter
lists against the tables (tests/core/test_abi.py, tests/track/test_layout_table.py).

Two kinds of dimensions:

- fixed (``dims`` all integers: the tracker's arrays, ``track/layout.py``): every offset is
  known at import, and the kernels read them as compile-time constants (:meth:`Table.offset`);
- per pipeline (``dims`` names ``"n"`` for each dimension, ``()`` for a scalar: the compiled
  path's constants, ``pipeline/compiled/abi.py``): :meth:`Table.pack` writes the arrays' values
  into the buffers and a ``layout`` int64 array holding, per slot, the offset and (up to two)
  dimensions, which the kernels read at run time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Field:
    name: str
    dtype: type
    dims: tuple = ("n",)  # integers (fixed) or "n" per dimension (given at packing), () scalar

    @property
    def fixed(self) -> bool:
        return all(isinstance(d, int) for d in self.dims)

    @property
    def size(self) -> int:
        return math.prod(self.dims)


class Table:
    """Fields in order, each in the buffer of its dtype (``buffers``, in argument order)."""

    def __init__(self, fields: tuple[Field, ...], buffers: tuple[type, ...]):
        self.fields = tuple(fields)
        self.buffers = tuple(np.dtype(b) for b in buffers)
        names = [f.name for f in self.fields]
        if len(set(names)) != len(names):
            raise ValueError("field names must be unique")
        for f in self.fields:
            if np.dtype(f.dtype) not in self.buffers:
                raise ValueError(f"{f.name}: no buffer for dtype {np.dtype(f.dtype)}")
        self._index = {name: i for i, name in enumerate(names)}

    def __len__(self) -> int:
        return len(self.fields)

    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    def slot(self, name: str) -> int:
        """The field's position in the table (its row of ``layout``)."""
        return self._index[name]

    def buffer_of(self, name: str) -> int:
        """The index of the buffer (in ``buffers``) the field lives in."""
        return self.buffers.index(np.dtype(self.fields[self._index[name]].dtype))

    # fixed dimensions: offsets known at import
    def offset(self, name: str) -> int:
        """Where a fixed-size field starts in its buffer: the sizes of the fields of the same
        dtype before it."""
        field = self.fields[self._index[name]]
        kind = np.dtype(field.dtype)
        at = 0
        for f in self.fields[: self._index[name]]:
            if np.dtype(f.dtype) == kind:
                at += f.size
        return at

    def end(self, name: str) -> int:
        return self.offset(name) + self.fields[self._index[name]].size

    def total(self, dtype) -> int:
        """The size of the buffer of ``dtype`` (fixed fields)."""
        kind = np.dtype(dtype)
        return sum(f.size for f in self.fields if np.dtype(f.dtype) == kind)

    # per-pipeline dimensions: packed with a layout
    def pack(self, values: dict) -> tuple[list[np.ndarray], np.ndarray] | None:
        """``(buffers, layout)`` for one array per field (by name): each field's values in
        the buffer of its dtype, in table order, and ``layout[3 * slot : 3 * slot + 3]`` its
        offset and its (at most two) dimensions, 1 for a missing one. None when a value does
        not have its field's dtype and number of dimensions: values are never converted."""
        if set(values) != set(self._index):
            missing = sorted(set(self._index) - set(values))
            extra = sorted(set(values) - set(self._index))
            raise ValueError(f"kernel constants: missing {missing}, unknown {extra}")
        parts: list[list[np.ndarray]] = [[] for _ in self.buffers]
        sizes = [0] * len(self.buffers)
        layout = np.zeros(3 * len(self.fields), dtype=np.int64)
        for slot, field in enumerate(self.fields):
            a = np.asarray(values[field.name])
            kind = self.buffers.index(np.dtype(field.dtype))
            if a.dtype != self.buffers[kind] or a.ndim != len(field.dims):
                return None
            shape = (*a.shape, 1, 1)[:2]
            layout[3 * slot : 3 * slot + 3] = (sizes[kind], *shape)
            parts[kind].append(a.ravel())
            sizes[kind] += a.size
        buffers = [
            np.ascontiguousarray(np.concatenate(p) if p else np.zeros(0), dtype=t)
            for p, t in zip(parts, self.buffers, strict=True)
        ]
        return buffers, layout
