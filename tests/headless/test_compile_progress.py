"""What a start that must compile says: a bar on a terminal, one line per kernel elsewhere,
warnings on a line of their own; and `run` preparing its kernels before the board opens."""

from __future__ import annotations

import io

from spiel_edge.runtime import compile_progress
from spiel_edge.runtime.compile_progress import Progress, about, estimate_seconds


class FakeTty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_plain_lines_for_the_journal():
    out = io.StringIO()
    progress = Progress(total=2, stream=out)
    assert not progress.tty
    progress("compile", "spiel_edge.pipeline.compiled.front._front_kernel", "(float64[:, :],)")
    assert out.getvalue() == ""  # a line per kernel compiled, not per start
    progress("compiled", "spiel_edge.pipeline.compiled.front._front_kernel", 12.5)
    progress("warning", "save:/x", "compiled kernel k not saved to /x (OSError: full)")
    progress.finish("done")
    lines = out.getvalue().splitlines()
    assert lines[0].startswith(
        "compiled 1/2: spiel_edge.pipeline.compiled.front._front_kernel (12.5 s"
    )
    assert lines[1] == "warning: compiled kernel k not saved to /x (OSError: full)"
    assert lines[2] == "done"
    assert "\r" not in out.getvalue() and "\x1b" not in out.getvalue()


def test_a_kernel_compiled_for_a_second_signature_counts_once():
    out = io.StringIO()
    progress = Progress(total=2, stream=out)
    for _ in range(3):
        progress("compiled", "spiel_edge.pipeline.stages.locate.locate_kernel", 0.5)
    assert progress.done == 1 and out.getvalue().splitlines()[-1].startswith("compiled 1/2: ")
    assert len(out.getvalue().splitlines()) == 1  # one line per kernel, not per signature


def test_a_bar_redrawn_in_place_on_a_terminal():
    out = FakeTty()
    progress = Progress(total=4, stream=out)
    assert progress.tty
    progress("compile", "spiel_edge.track.step.step_kernel", "()")
    progress("compiled", "spiel_edge.track.step.step_kernel", 1.0)
    progress.say("a line of its own")
    progress.finish("ready")
    text = out.getvalue()
    assert "[######------------------] 1/4" in text and "track.step.step_kernel" in text
    assert "\r\x1b[Ka line of its own\n" in text
    assert text.endswith("ready\n")
    assert "compiled 1/4" not in text  # no journal lines on a terminal


def test_the_estimate_scales_with_what_is_missing_and_the_machine():
    full = estimate_seconds(10, 10, "x86_64")
    assert full == compile_progress.FULL_COMPILE_S
    assert estimate_seconds(5, 10, "x86_64") == full / 2
    assert estimate_seconds(10, 10, "aarch64") > full
    assert about(20) == "about 20 s" and about(5) == "about 10 s"
    assert about(600) == "about 7-15 min"


def test_a_broken_stream_never_stops_the_compile():
    class Gone(io.StringIO):
        def write(self, text):
            raise OSError("terminal hung up")

    progress = Progress(total=1, stream=Gone())
    progress("compiled", "k", 1.0)
    progress.finish("done")  # no exception


def test_run_prepares_its_kernels_from_the_cache_before_the_board(monkeypatch):
    """Everything cached (the suite has run the pipeline by now, or compiles it here once):
    the preparation compiles nothing and says nothing."""
    from spiel_edge.profile.schema import load_profile
    from spiel_edge.runtime import first_start

    profile = load_profile()
    first_start.prepare_for_run(profile, None, 4, True)  # a cold cache compiles here, once
    out = io.StringIO()
    again = first_start.prepare_for_run(profile, None, 4, True, stream=out)
    assert again["compiled"] is False and out.getvalue() == ""


def test_the_service_hears_of_each_kernel_and_gets_more_time(tmp_path):
    import socket

    from spiel_edge.service.systemd import Notifier

    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(path)
        progress = Progress(total=3, stream=io.StringIO())
        progress.notifier = Notifier({"NOTIFY_SOCKET": path})
        progress("compiled", "spiel_edge.track.step.step_kernel", 2.0)
        message = server.recv(4096).decode()
    assert "STATUS=compiling kernels: 1/3 (track.step.step_kernel)" in message
    assert "EXTEND_TIMEOUT_USEC=120000000" in message


def test_a_warmup_step_in_a_child_reports_its_kernels():
    from spiel_edge.runtime import warmup

    seen = []
    report = warmup.run_child("stream", lambda *event: seen.append(event))
    names = {"spiel_edge.protocol._cobs_numba.decode", "spiel_edge.protocol._cobs_numba.encode"}
    assert names <= set(report["kernels"])
    assert set(report["compiled"]) | set(report["cache_hits"]) >= names
    assert {name for event, name, _ in seen if event == "compiled"} == set(report["compiled"])


def test_a_child_past_its_memory_budget_hands_the_kernel_to_a_fresh_one(tmp_path, monkeypatch):
    from spiel_edge.runtime import warmup, warmup_child

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))  # empty: the kernel compiles
    monkeypatch.setenv(warmup_child.ENV_BUDGET, "0")  # every child is past it at once
    children = []
    one_child = warmup_child._one_child
    monkeypatch.setattr(
        warmup_child, "_one_child", lambda *a: children.append(one_child(*a)) or children[-1]
    )
    seen = []
    report = warmup.run_child("csv", lambda *event: seen.append(event))
    kernel = "spiel_edge.recordings.spiel_csv._scan_integers"
    # the first child stops before compiling, naming the kernel; the second compiles it
    assert [status for _, status, _ in children] == [warmup_child.RESTART, 0]
    assert children[0][2][0] == kernel
    assert [(event, name) for event, name, _ in seen] == [("compile", kernel), ("compiled", kernel)]
    assert report["compiled"] == [kernel] and kernel in report["kernels"]
    assert kernel not in report["cache_hits"]
