"""A real-time scheduling class for the streaming threads (``--realtime PRIORITY``).

On a loaded computer the latency from an acquisition to its record is set by the scheduler,
not by our work: a thread that wakes for a record waits for a time slice behind every other
runnable task (on 2 cores with two busy processes beside the robot's five, the fused
record's p95 went from 2.3 to 6.2-7.1 ms; docs/robot.md). Linux's SCHED_FIFO runs such a
thread as soon as it wakes, ahead of every normal task, at the price of starving them while
it runs; the kernel's real-time throttling (``kernel.sched_rt_runtime_us``, 95 % by default)
keeps a runaway from taking a whole core. Our threads sleep between acquisitions, so a low
priority (10) is plenty and stays below the kernel's own real-time threads.

The class applies to the calling thread and to the threads it starts from then on (Linux
threads inherit it), so callers request it once their kernels are compiled (a compile is
long work that should not run ahead of the rest of the robot) and before they open the
links and sessions whose threads carry the records.
"""

from __future__ import annotations

import logging
import os

log = logging.getLogger(__name__)

MIN_PRIORITY, MAX_PRIORITY = 1, 99


def request_realtime(priority: int) -> str | None:
    """Put the calling thread (and the threads it starts later) in SCHED_FIFO at
    ``priority``; None when done, else why not (the caller goes on with normal scheduling)."""
    if not MIN_PRIORITY <= int(priority) <= MAX_PRIORITY:
        raise ValueError(f"real-time priority {priority} is outside {MIN_PRIORITY}..{MAX_PRIORITY}")
    setter = getattr(os, "sched_setscheduler", None)
    if setter is None or not hasattr(os, "SCHED_FIFO"):
        return "this system has no SCHED_FIFO (Linux only)"
    try:
        setter(0, os.SCHED_FIFO, os.sched_param(int(priority)))
    except PermissionError:
        return (
            f"no permission for SCHED_FIFO priority {priority}: run it as the systemd unit "
            f"(packaging/systemd: LimitRTPRIO) or allow rtprio {priority} for the user "
            "(/etc/security/limits.conf)"
        )
    except OSError as exc:
        return f"SCHED_FIFO priority {priority} refused: {exc}"
    return None


def apply_realtime(priority: int | None) -> bool:
    """``--realtime``: request it (nothing when None) and say what came of it; a refusal is
    a warning, the command goes on with normal scheduling. True when in effect."""
    if priority is None:
        return False
    why = request_realtime(priority)
    if why is None:
        log.info("scheduling: SCHED_FIFO priority %d", priority)
        return True
    log.warning("--realtime %d not in effect, normal scheduling: %s", priority, why)
    return False
