"""The audit log: one JSON line per laser state change and per bench-changing command.

Each line says who (transport, uid, user, pid or TCP peer), when (UTC ISO time and Unix time),
what (the method and its parameters) and the outcome. Lines are flushed at once: the log is
what a person reads after an incident, so it must hold the last command before a crash.
`set_view` arrives at navigator rates, so consecutive views from one caller are summarised (the
first is written, then one line per `view_summary_s` with the count and the last sequence number).
"""

from __future__ import annotations

import datetime as dt
import json
import threading
import time
from pathlib import Path
from typing import IO, Any

from .protocol import _sanitise


class AuditLog:
    def __init__(self, path: Path | None, *, view_summary_s: float = 1.0) -> None:
        self.path = path
        self._file: IO[str] | None = None
        self._lock = threading.Lock()  # jobs finish on worker threads
        self.view_summary_s = view_summary_s
        self._views: dict[str, dict[str, Any]] = {}
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file = path.open("a", encoding="utf-8")

    def write(self, who: dict[str, Any], what: str, **details: Any) -> None:
        now = time.time()
        record = {
            "time": dt.datetime.fromtimestamp(now, dt.UTC).isoformat(timespec="milliseconds"),
            "unix_s": round(now, 3),
            "who": who,
            "what": what,
            **details,
        }
        line = json.dumps(_sanitise(record), allow_nan=False, default=str)
        with self._lock:
            if self._file is not None:
                self._file.write(line + "\n")
                self._file.flush()

    def view(self, who: dict[str, Any], seq: int, view: dict[str, Any]) -> None:
        key = json.dumps(who, sort_keys=True, default=str)
        now = time.monotonic()
        pending = self._views.get(key)
        if pending is None or now - pending["since"] >= self.view_summary_s:
            self.flush_views(key)
            self.write(who, "set_view", seq=seq, view=view)
            self._views[key] = {"since": now, "count": 0, "who": who}
        else:
            pending["count"] += 1
            pending["last_seq"], pending["last_view"] = seq, view

    def flush_views(self, only: str | None = None) -> None:
        for key in [only] if only else list(self._views):
            pending = self._views.pop(key, None) if key else None
            if pending and pending["count"]:
                self.write(pending["who"], "set_view (summary)", count=pending["count"],
                           last_seq=pending["last_seq"], last_view=pending["last_view"])

    def tick(self) -> None:
        """Write summaries whose interval has passed (called from the control loop)."""
        now = time.monotonic()
        for key, pending in list(self._views.items()):
            if now - pending["since"] >= self.view_summary_s:
                self.flush_views(key)

    def close(self) -> None:
        self.flush_views()
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None
