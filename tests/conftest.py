import numpy as np
import pytest

from spiel_edge.profile.schema import load_profile


@pytest.fixture(scope="session")
def profile():
    return load_profile("spiel-icra23")


@pytest.fixture(scope="session")
def subset():
    from spiel_edge.data import load_subset

    return load_subset()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="session", autouse=True)
def _model_cache(tmp_path_factory):
    """Verified model weights go to a temporary folder, not the user's cache."""
    import os

    os.environ["SPIEL_EDGE_MODEL_CACHE"] = str(tmp_path_factory.mktemp("verified-models"))


def _descendants() -> dict[int, str]:
    """This process's living descendants (pid -> command name), from /proc; {} without it."""
    import os

    parent: dict[int, int] = {}
    names: dict[int, str] = {}
    try:
        pids = [int(p) for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return {}
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as fh:
                stat = fh.read()
        except OSError:
            continue
        name, rest = stat[stat.index("(") + 1 : stat.rindex(")")], stat[stat.rindex(")") + 2 :]
        state, ppid = rest.split()[:2]
        if state not in ("Z", "X"):  # a zombie is gone already (its parent reaps it)
            parent[pid], names[pid] = int(ppid), name
            if int(ppid) == os.getpid() and _interpreter_helper(pid):
                names.pop(pid)  # the helper itself; what it forks (pool workers) still counts
    me, out = os.getpid(), {}
    for pid in names:
        p, hops = parent.get(pid), 0
        while p is not None and p != me and hops < 64:
            p, hops = parent.get(p), hops + 1
        if p == me:
            out[pid] = names[pid]
    return out


def _interpreter_helper(pid: int) -> bool:
    """multiprocessing's forkserver and resource tracker: started once, kept for the process's
    life and reused (the parallel replay's workers come from the forkserver), not a leak."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return b"multiprocessing" in fh.read()
    except OSError:
        return False


@pytest.fixture(scope="module", autouse=True)
def _no_process_outlives_its_module():
    """Emulators and child processes never outlive their test module: any descendant started
    while the module ran and still alive after its fixtures were torn down is killed (by its
    pid: a process this run started) and named in a warning. A left-over emulator busy-looping a
    core once made three later tests fail."""
    import contextlib
    import os
    import signal
    import warnings

    before = _descendants()
    yield
    left = {pid: name for pid, name in _descendants().items() if pid not in before}
    for pid in left:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
    if left:
        warnings.warn(
            f"processes outlived their test module and were killed: {sorted(left.items())}",
            stacklevel=1,
        )


@pytest.fixture(autouse=True)
def _log_handlers_end_with_their_test():
    """``main()`` points the root logger at the stderr it sees, a test's capture; a later test's
    threads would log into that closed stream ("Logging error ... I/O operation on closed
    file"). Handlers a test added are removed when it ends."""
    import logging

    root = logging.getLogger()
    before = list(root.handlers)
    yield
    for handler in root.handlers[:]:
        if handler not in before:
            root.removeHandler(handler)
