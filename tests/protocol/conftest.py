from __future__ import annotations

from pathlib import Path

import pytest

from tests.protocol.c_driver import build, compiler


@pytest.fixture(scope="session")
def driver(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The C test driver, compiled once per session with the system compiler."""
    cc = compiler()
    if cc is None:
        pytest.skip("no C compiler found (set CC or install gcc/cc/clang)")
    exe = tmp_path_factory.mktemp("c") / "sp_driver"
    result = build(cc, exe)
    assert result.returncode == 0, result.stderr
    return exe
