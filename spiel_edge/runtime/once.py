"""One log line per distinct problem, not one per acquisition: a board that sends a wrong
shape 100 times a second gets one error and a count, not a flooded journal."""

from __future__ import annotations

import logging
from collections import Counter

MAX_KINDS = 64  # distinct problems remembered; beyond, new ones are still logged once each


class OncePerProblem:
    def __init__(self, logger: logging.Logger, level: int = logging.ERROR) -> None:
        self.logger, self.level = logger, level
        self.counts: Counter[str] = Counter()

    def log(self, problem: str, detail: str = "") -> bool:
        """Log ``problem`` the first time (with ``detail``); later only count it. True when
        it was logged."""
        first = problem not in self.counts
        if first or len(self.counts) < MAX_KINDS:
            self.counts[problem] += 1
        if first:
            suffix = f" ({detail})" if detail else ""
            self.logger.log(self.level, "%s%s; repeats are counted, not logged", problem, suffix)
        else:
            self.logger.debug("%s%s", problem, f" ({detail})" if detail else "")
        return first

    def summary(self) -> list[str]:
        return [f"{n} x {problem}" for problem, n in self.counts.items() if n > 1]
