"""``--realtime PRIORITY``: SCHED_FIFO for the streaming threads once the kernels are ready;
refused (no right) it is a warning and the command goes on with normal scheduling."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import textwrap

import pytest

from spiel_edge.cli import main
from spiel_edge.errors import ConfigError
from spiel_edge.runtime import realtime

linux_fifo = pytest.mark.skipif(
    not hasattr(os, "sched_setscheduler"), reason="SCHED_FIFO is Linux's"
)


@pytest.mark.parametrize("priority", [0, 100, -3])
def test_a_priority_outside_1_to_99_is_refused(priority):
    with pytest.raises(ValueError, match="outside 1..99"):
        realtime.request_realtime(priority)


@linux_fifo
def test_no_permission_is_a_reason_naming_the_remedy(monkeypatch, caplog):
    def refuse(pid, policy, param):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    why = realtime.request_realtime(10)
    assert "no permission" in why and "LimitRTPRIO" in why and "limits.conf" in why
    with caplog.at_level(logging.WARNING, logger="spiel_edge.runtime.realtime"):
        assert realtime.apply_realtime(10) is False
    assert "--realtime 10 not in effect, normal scheduling" in caplog.text


@linux_fifo
def test_granted_it_asks_fifo_for_the_calling_thread(monkeypatch):
    calls = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda *a: calls.append(a))
    assert realtime.apply_realtime(None) is False and not calls  # not asked: nothing done
    assert realtime.apply_realtime(7) is True
    ((pid, policy, param),) = calls
    assert (pid, policy, param.sched_priority) == (0, os.SCHED_FIFO, 7)


@linux_fifo
def test_threads_started_afterwards_inherit_it():
    """In a child process (the test runner itself stays normal): the thread that asked and a
    thread it starts afterwards run SCHED_FIFO; a thread started before does not."""
    code = textwrap.dedent(
        """
        import os, threading
        from spiel_edge.runtime.realtime import request_realtime
        seen = {}
        go = threading.Event()
        def probe(name, wait):
            if wait:
                go.wait()
            seen[name] = os.sched_getscheduler(0) == os.SCHED_FIFO
        before = threading.Thread(target=probe, args=("before", True))
        before.start()
        why = request_realtime(5)
        after = threading.Thread(target=probe, args=("after", False))
        after.start(); after.join(); go.set(); before.join()
        print(why or "granted", os.sched_getscheduler(0) == os.SCHED_FIFO, seen["after"],
              seen["before"])
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    ).stdout.split()
    if out[0] != "granted":
        pytest.skip(f"SCHED_FIFO not allowed here: {' '.join(out)}")
    assert out[1:] == ["True", "True", "False"]


def test_run_asks_after_the_kernels_and_a_refusal_does_not_stop_it(monkeypatch, tmp_path, capsys):
    asked = []

    def refuse(priority):
        asked.append(priority)
        return "no permission (test)"

    monkeypatch.setattr(realtime, "request_realtime", refuse)
    out = tmp_path / "r.ndjson"
    status = main(["run", "--port", "sim://", "--frames", "3", "--realtime", "9", "-o", out])
    assert status == 0 and asked == [9]
    assert len(out.read_text().splitlines()) == 3
    assert "--realtime 9 not in effect, normal scheduling: no permission" in capsys.readouterr().err


def test_run_robot_and_fuse_take_it(monkeypatch, tmp_path):
    asked = []
    monkeypatch.setattr(realtime, "request_realtime", lambda p: asked.append(p) or "refused")
    out = tmp_path / "fused.ndjson"
    status = main(["run", "--robot", "virtual-4", "--frames", "3", "--realtime", "4", "-o", out])
    assert status == 0 and asked == [4] and len(out.read_text().splitlines()) == 3
    pytest.importorskip("zenoh", reason="the 'zenoh' extra is not installed")
    import spiel_edge.robot.zenoh_fuse as zf

    seen = []

    class NoZenoh:  # fuse asks before it opens its Zenoh session
        def __init__(self, *a, **k):
            seen.append(list(asked))
            raise ConfigError("no session in this test")

    monkeypatch.setattr(zf, "ZenohFuse", NoZenoh)
    status = main(["fuse", "--robot", "virtual-4", "--realtime", "6", "-o", tmp_path / "f.ndjson"])
    assert status == 2 and seen == [[4, 6]]
