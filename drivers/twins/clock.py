"""Clocks for twins and drivers: real monotonic time, or a manual clock a test advances."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

Clock = Callable[[], float]

real_clock: Clock = time.monotonic


class ManualClock:
    """Time that moves only when a test calls `advance` (thread-safe)."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._now_s = start_s
        self._lock = threading.Lock()

    def __call__(self) -> float:
        """The time now (s)."""
        with self._lock:
            return self._now_s

    def advance(self, dt_s: float) -> float:
        """Move time forward by `dt_s` (s, >= 0; ValueError otherwise); returns the new time."""
        if dt_s < 0:
            raise ValueError("time does not run backwards")
        with self._lock:
            self._now_s += dt_s
            return self._now_s
