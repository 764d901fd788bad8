"""tools/release/build_wheels.py: a pure wheel becomes a tagged wheel carrying the kernels and
their manifest, with a RECORD pip accepts. A wheel built for real is checked when
SPIEL_TEST_WHEEL names it (opt-in: building one compiles every kernel)."""

from __future__ import annotations

import base64
import csv
import hashlib
import io
import json
import os
import zipfile
from pathlib import Path

import pytest

from tools.release import build_wheels

INFO = "spiel_edge-0.1.0.dist-info"


def _pure_wheel(path: Path) -> Path:
    wheel = path / "spiel_edge-0.1.0-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as zf:
        zf.writestr("spiel_edge/__init__.py", "x = 1\n")
        zf.writestr(
            f"{INFO}/WHEEL", "Wheel-Version: 1.0\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
        )
        zf.writestr(f"{INFO}/RECORD", "stale\n")
    return wheel


def _check_record(zf: zipfile.ZipFile) -> None:
    rows = list(csv.reader(io.StringIO(zf.read(f"{INFO}/RECORD").decode())))
    listed = {row[0] for row in rows}
    assert listed == set(zf.namelist())
    for name, digest, size in rows:
        if name.endswith("RECORD"):
            assert digest == size == ""
            continue
        data = zf.read(name)
        want = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        assert digest == f"sha256={want}" and int(size) == len(data)


def test_a_pure_wheel_is_packaged_with_its_kernels(tmp_path):
    kernels = tmp_path / "kernels"
    (kernels / "spiel_edge/pipeline").mkdir(parents=True)
    (kernels / "spiel_edge/pipeline/front._front-10.py311.nbi").write_bytes(b"index")
    (kernels / "spiel_edge/pipeline/front._front-10.py311.1.nbc").write_bytes(b"data")
    ident = {"python": "cpython-311", "machine": "x86_64", "numba": "0.68.1", "llvmlite": "0.50.0"}
    ident["platform"] = "manylinux_2_27_x86_64.manylinux_2_28_x86_64"
    wheel = build_wheels.package(_pure_wheel(tmp_path), kernels, ident, tmp_path / "out")
    assert wheel.name == (
        "spiel_edge-0.1.0-cp311-cp311-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl"
    )
    with zipfile.ZipFile(wheel) as zf:
        tags = zf.read(f"{INFO}/WHEEL").decode()
        assert "Tag: cp311-cp311-manylinux_2_27_x86_64" in tags and "py3-none-any" not in tags
        assert "Root-Is-Purelib: false" in tags
        manifest = json.loads(zf.read("spiel_edge/_kernels/manifest.json"))
        assert manifest["cpu"] == "generic" and manifest["numba"] == "0.68.1"
        for rel, digest in manifest["files"].items():
            assert hashlib.sha256(zf.read(f"spiel_edge/_kernels/{rel}")).hexdigest() == digest
        assert len(manifest["files"]) == 2
        _check_record(zf)


def test_numbas_platform_tag_is_taken_from_its_wheel_metadata():
    meta = "Wheel-Version: 1.0\nTag: cp311-cp311-manylinux_2_27_aarch64\nTag: cp311-cp311-manylinux_2_28_aarch64\n"
    assert build_wheels.platform_tag(meta) == "manylinux_2_27_aarch64.manylinux_2_28_aarch64"
    with pytest.raises(SystemExit):
        build_wheels.platform_tag("Wheel-Version: 1.0\n")


@pytest.mark.skipif(not os.environ.get("SPIEL_TEST_WHEEL"), reason="set SPIEL_TEST_WHEEL=<wheel>")
def test_a_built_release_wheel_carries_every_kernel_it_lists():
    with zipfile.ZipFile(os.environ["SPIEL_TEST_WHEEL"]) as zf:
        manifest = json.loads(zf.read("spiel_edge/_kernels/manifest.json"))
        assert manifest["cpu"] == "generic" and len(manifest["files"]) > 50
        for rel, digest in manifest["files"].items():
            assert hashlib.sha256(zf.read(f"spiel_edge/_kernels/{rel}")).hexdigest() == digest
        _check_record(zf)
