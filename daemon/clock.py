"""Our time base, injected wherever the daemon needs "now": received_ns, quiet periods, job times.

SystemClock is the wall clock. ScaledClock runs faster than real time from a chosen start, so `rsucal demo`
and the benchmarks can replay minutes of traffic in seconds while the daemon's timers behave as in the field.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    def now_ns(self) -> int:
        """Nanoseconds since the Unix epoch, in this clock's time base."""
        ...


class SystemClock:
    """The wall clock (time.time_ns)."""

    def now_ns(self) -> int:
        return time.time_ns()


class ScaledClock:
    """Starts at `start_ns` and runs `rate` times faster than the monotonic clock."""

    def __init__(self, start_ns: int, rate: float = 1.0) -> None:
        if not rate > 0.0:
            raise ValueError(f"rate = {rate} must be positive")
        self.start_ns = start_ns
        self.rate = rate
        self._t0_ns = time.monotonic_ns()

    def now_ns(self) -> int:
        return self.start_ns + int((time.monotonic_ns() - self._t0_ns) * self.rate)

    def sleep_until(self, stamp_ns: int, stop: threading.Event) -> bool:
        """Wait until now_ns() >= stamp_ns; False when `stop` was set first."""
        while True:
            remaining_ns = stamp_ns - self.now_ns()
            if remaining_ns <= 0:
                return True
            if stop.wait(remaining_ns / self.rate / 1e9):
                return False
