"""Layers that hold: spiel_edge's packages form no cycle, and every import goes down the
declared layer order (an arrow up fails even before it closes a cycle). The module-level
cycle test (test_layout.py) cannot see a package cycle made of acyclic module imports.

The order follows the data (bytes -> frames -> acquisitions -> ... -> outputs) with the run
on top: a package imports only packages of a lower layer, never one of its own layer."""

from __future__ import annotations

import pytest

from tests.house.imports import cycles, import_graph, package_graph, package_of

LAYERS = (
    # foundations: no spiel_edge package below them
    ("errors", "compat", "_abi", "_early", "_numba_gate", "_shipped", "_tiers", "data"),
    ("__init__",),  # the version and the early environment
    ("safety", "link", "_kernel_cache", "_cache_load"),  # file rules, port URLs, numba cache
    ("_kernel_layers",),
    ("_jit", "profile"),
    ("protocol",),  # frames: the codec (its COBS kernel uses _jit)
    ("board_config", "device", "messages", "pipeline", "track"),
    ("recordings", "view"),
    ("outputs",),
    ("runtime",),  # the live loop and replay: opens a device, runs the pipeline, writes sinks
    ("calibrate", "robot"),
    ("sim",),  # the virtual board (its robot scene reads the robot file)
    ("measure", "service"),
    ("cli",),
)


@pytest.fixture(scope="module")
def packages():
    return package_graph(import_graph())


def test_every_package_has_a_layer(packages):
    declared = [name for layer in LAYERS for name in layer]
    assert len(declared) == len(set(declared)), "a package is declared twice"
    assert set(packages) - set(declared) == set(), "a new package: give it a layer here"
    assert set(declared) - set(packages) == set(), "LAYERS names a package that is gone"


def test_no_package_cycle(packages):
    graph = {a: set(arrows) for a, arrows in packages.items()}
    assert cycles(graph) == []


def test_every_import_goes_down_the_layers(packages):
    rank = {name: i for i, layer in enumerate(LAYERS) for name in layer}
    up = sorted(
        f"{module} -> {target} ({a} layer {rank[a]}, {b} layer {rank[b]})"
        for a, arrows in packages.items()
        for b, pairs in arrows.items()
        if rank[b] >= rank[a]
        for module, target in pairs
    )
    assert up == [], "imports that do not go down:\n" + "\n".join(up)


def test_the_wheel_imports_no_tool_and_the_protocol_no_host():
    graph = import_graph()
    wrong = sorted(
        f"{m} -> {t}"
        for m, targets in graph.items()
        for t in targets
        if (package_of(m) is not None and t.split(".")[0] == "tools")
        or (package_of(m) == "protocol" and package_of(t) not in ("protocol", "_jit"))
    )  # the protocol's COBS kernel compiles through the project's one numba decorator
    assert wrong == []


def test_the_layer_check_sees_an_arrow_up_and_a_package_cycle():
    graph = {
        "spiel_edge.runtime.loop": {"spiel_edge.sim.options"},  # up: runtime asks sim
        "spiel_edge.sim.options": {"spiel_edge.errors"},
        "spiel_edge.outputs.a": {"spiel_edge.recordings.b"},  # a cycle of acyclic modules
        "spiel_edge.recordings.c": {"spiel_edge.outputs.d"},
        "spiel_edge.outputs.d": set(),
        "spiel_edge.recordings.b": set(),
        "spiel_edge.errors": set(),
    }
    packages = package_graph(graph)
    assert cycles(graph) == []  # the module-level test sees nothing
    assert cycles({a: set(arrows) for a, arrows in packages.items()}) == [["outputs", "recordings"]]
    rank = {name: i for i, layer in enumerate(LAYERS) for name in layer}
    assert rank["sim"] > rank["runtime"] and "sim" in packages["runtime"]
