"""The recent errors `status` lists: a failed job, a frame the panel refused, a crashed frame
worker, a lost SLM output, a method that failed inside the daemon.

The parts report here through a callback given at construction (`ErrorList.note`), never by
reaching into the daemon; `status` shows the last `KEPT` after the devices' own errors.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

KEPT = 20  # entries kept: enough to see what led up to a fault, bounded whatever happens


class ErrorList:
    """The newest `kept` errors, each {"time_s", "source", "message"}, oldest first."""

    def __init__(self, kept: int = KEPT) -> None:
        self._entries: deque[dict[str, Any]] = deque(maxlen=kept)
        # Jobs finish on their runners' threads; the control loop and requests note the rest.
        self._lock = threading.Lock()

    def note(self, source: str, message: str) -> None:
        """One error from `source` ("frame worker", "slm", "job 7 (focus)", ...), stamped now
        (Unix time)."""
        entry = {"time_s": time.time(), "source": source, "message": message}
        with self._lock:
            self._entries.append(entry)

    def entries(self) -> list[dict[str, Any]]:
        """The errors kept, oldest first (a copy: `status` reads it while parts append)."""
        with self._lock:
            return list(self._entries)
