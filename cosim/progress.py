"""Progress of a long command: a progress bar on a terminal, a log line every so often without one.

Contract: `Heartbeat(every_s)()` is true once every `every_s` seconds (the first call included): when a command
without a terminal logs its line. `headless()` tells whether stderr is not a terminal (no progress bar then).
"""

from __future__ import annotations

import sys
import time


def headless() -> bool:
    return not sys.stderr.isatty()


class Heartbeat:
    """True once every `every_s` seconds (the first call included): when a command without a terminal (no
    progress bar) logs a line."""

    def __init__(self, every_s: float) -> None:
        self.every_s = every_s
        self.last = -float("inf")

    def __call__(self) -> bool:
        now = time.monotonic()
        if now - self.last >= self.every_s:
            self.last = now
            return True
        return False
