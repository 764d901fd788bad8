"""The hostile-input suite: every case runs a command (or a reader) the way a careless or
hostile user would, and checks the two invariants of docs/reliability.md: no traceback and
no data lost. Cases are counted in the report (``pytest tests/hostile -q``)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from spiel_edge.cli import main

ALLOWED_STATUS = {0, 1, 2, 130}


class Ran:
    def __init__(self, status: int, out: str, err: str) -> None:
        self.status, self.out, self.err = status, out, err

    def __repr__(self) -> str:
        return f"status {self.status}\nstdout: {self.out[-500:]}\nstderr: {self.err[-1500:]}"


def assert_clean(ran: Ran) -> None:
    """No traceback, no last-resort 'internal error', a documented status, short messages."""
    assert "Traceback" not in ran.err, ran
    assert "internal error" not in ran.err, ran
    assert ran.status in ALLOWED_STATUS, ran
    assert all(len(line) < 2000 for line in ran.err.splitlines()), "a huge line was echoed"


@pytest.fixture
def cli(capsys):
    """``cli("replay", path, ...)`` -> Ran, checked clean."""

    def run(*args: object) -> Ran:
        capsys.readouterr()
        status = main([str(a) for a in args])
        out, err = capsys.readouterr()
        ran = Ran(status, out, err)
        assert_clean(ran)
        return ran

    return run


def digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@pytest.fixture
def precious(tmp_path):
    """A file a user cares about; ``check()`` asserts it is unchanged."""
    path = tmp_path / "precious.ndjson"
    path.write_text('{"keep": "me"}\n')
    before = digest(path)

    class Precious:
        def __init__(self) -> None:
            self.path = path

        def check(self) -> None:
            assert path.exists() and digest(path) == before, "data loss: the file changed"

    return Precious()


@pytest.fixture(scope="session")
def csv_folder(tmp_path_factory, subset):
    from tests.core.spiel_csv_fixture import write_spiel_csv

    root = tmp_path_factory.mktemp("csv")
    return write_spiel_csv(subset, root, indices=range(3))


@pytest.fixture(scope="session")
def recording(tmp_path_factory, subset) -> Path:
    """A finalized MCAP of 300 live-like acquisitions (one background, as `run --record`)."""
    from spiel_edge.recordings.mcap_writer import McapSink

    path = tmp_path_factory.mktemp("mcap") / "rec.mcap"
    with McapSink(path) as sink:
        sink.log_time_from_stamp = True  # the same bytes on every run: reproducible offsets
        for i in range(300):
            k = i % len(subset.frames)
            meta = {"seq": i, "timestamp_ns": 1_000_000 + i, "background": subset.backgrounds[0]}
            sink.write_acquisition(meta, subset.frames[k])
            sink.write({"seq": i, "position_mm": [1.0, 2.0, 3.0], "reason": None})
    return path
