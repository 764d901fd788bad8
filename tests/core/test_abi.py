"""The compiled path's argument table (pipeline/compiled/abi.py) against the code that reads
it: every view function reads each constant from its dtype's buffer with its dimensions, in
the order of the kernels' parameters, and every slot number is the table's."""

from __future__ import annotations

import ast
import inspect

import numpy as np
import pytest

from spiel_edge._abi import Field, Table
from spiel_edge.pipeline.compiled import abi, front, one_target, several_targets, steps

BUFFER_NAMES = {"f64": np.float64, "f32": np.float32, "i64": np.int64, "flags": np.bool_}


def _function(module, name: str) -> ast.FunctionDef:
    tree = ast.parse(inspect.getsource(module))
    return next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == name)


def _views(name: str) -> list[str]:
    """The constants a view function returns, in order, each checked against the table."""
    ret = next(n for n in ast.walk(_function(abi, name)) if isinstance(n, ast.Return))
    out = []
    for item in ret.value.elts:
        if isinstance(item, ast.Call):  # view_Nd(buffer, layout, L_NAME)
            ndim = int(item.func.id.removeprefix("view_").removesuffix("d"))
            buffer, slot = item.args[0].id, item.args[2].id
        else:  # a scalar: buffer[layout[3 * L_NAME]]
            ndim, buffer, slot = 0, item.value.id, item.slice.slice.right.id
        field = abi.CONSTANTS.fields[getattr(abi, slot)]
        assert slot == f"L_{field.name.upper()}"
        assert len(field.dims) == ndim, field.name
        assert BUFFER_NAMES[buffer] == field.dtype, field.name
        out.append(field.name)
    return out


def _parameters(kernel) -> list[str]:
    return list(inspect.signature(kernel.py_func).parameters)


def test_every_slot_number_is_the_tables():
    for i, field in enumerate(abi.CONSTANTS.fields):
        assert getattr(abi, f"L_{field.name.upper()}") == i == abi.CONSTANTS.slot(field.name)
    for prefix, names in (
        ("I_", abi.INTS),
        ("F_", abi.FLOATS),
        ("PRIOR_", abi.PRIORS),
        ("TIMING_", abi.TIMINGS),
    ):
        for i, name in enumerate(names):
            assert getattr(abi, prefix + name.upper()) == i


def test_the_views_follow_the_table_and_the_kernels_read_them_by_slot():
    back = _views("back_views")
    scene = _views("scene_views")
    front_views = _views("front_views")
    assert back + scene + front_views == list(abi.CONSTANTS.names())
    # the kernels read the back views as cs[L_NAME]: the slot is the tuple's index
    for module in (one_target, several_targets, steps):
        for node in ast.walk(ast.parse(inspect.getsource(module))):
            if isinstance(node, ast.Subscript) and getattr(node.value, "id", "") == "cs":
                assert abi.CONSTANTS.names()[getattr(abi, node.slice.id)] in back
    unpack = next(
        n
        for n in ast.walk(_function(several_targets, "_scene_steps"))
        if isinstance(n, ast.Assign) and getattr(n.value, "id", "") == "scene"
    )
    assert [t.id for t in unpack.targets[0].elts] == scene


def test_the_front_settings_reach_the_front_kernel_in_its_order():
    call = next(
        n
        for n in ast.walk(_function(front, "packed_front"))
        if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "_front_kernel"
    )
    names = []
    for arg in call.args:
        node = arg.left if isinstance(arg, ast.Compare) else arg
        if isinstance(node, ast.Subscript) and node.value.id in ("fi", "ff"):
            table = abi.FRONT_INTS if node.value.id == "fi" else abi.FRONT_FLOATS
            names.append(table[getattr(abi, node.slice.id)])
    params = _parameters(front._front_kernel)
    assert params[2 : 2 + len(names)] == names
    assert sorted(names) == sorted(abi.FRONT_INTS + abi.FRONT_FLOATS)


def test_the_tables_offsets_and_packing():
    t = Table(
        (Field("a", np.float64, (2, 3)), Field("b", np.int64, (4,)), Field("c", np.float64, (5,))),
        (np.float64, np.int64),
    )
    assert (t.offset("a"), t.offset("b"), t.offset("c")) == (0, 0, 6)
    assert (t.end("c"), t.total(np.float64), t.total(np.int64)) == (11, 11, 4)
    v = Table(
        (Field("m", np.float32, ("n", "n")), Field("s", np.float64, ())), (np.float64, np.float32)
    )
    (f64, f32), layout = v.pack({"m": np.ones((2, 3), np.float32), "s": 2.5})
    assert f32.size == 6 and f64.tolist() == [2.5] and layout.tolist() == [0, 2, 3, 0, 1, 1]
    assert v.pack({"m": np.ones((2, 3)), "s": 2.5}) is None  # float64, not float32: refused
    with pytest.raises(ValueError, match="missing"):
        v.pack({"m": np.ones((2, 3), np.float32)})
