"""Shared helpers for daemon tests: polling with a deadline (never fixed sleeps) and free loopback ports."""

from __future__ import annotations

import time
from collections.abc import Callable

from daemon.bus import free_loopback_port as free_port

__all__ = ["free_port", "wait_until"]


def wait_until(predicate: Callable[[], object], timeout_s: float = 10.0, interval_s: float = 0.01) -> None:
    """Poll `predicate` until it returns something truthy; AssertionError after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        if predicate():
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout_s} s")
        time.sleep(interval_s)
