"""The audit log: one JSON line per laser state change and per bench-changing command.

Each line says who (transport, uid, user, pid or TCP peer), when (UTC ISO time and Unix time),
what (the method and its parameters) and the outcome. Lines are flushed at once: the log is
what a person reads after an incident, so it must hold the last command before a crash.

Two kinds of request arrive faster than a person reads, and are summarised per `summary_s`
window (the first is written, then one line with the exact count of the rest):
- `set_view` at navigator rates, per caller (the count and the last sequence number);
- refusals, per method and error code whatever the caller (any client can send them, and a
  client can open many connections): the first compactly (parameters cut to
  `PARAMS_CHARS`), then "N more like this".
The file is rotated by size (`audit.jsonl` -> `audit.jsonl.1` ...), so the log never holds more
than `max_bytes * (backups + 1)` bytes on disk.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

from nhfd.config import AuditSettings

from .protocol import sanitise

# A refused request's parameters and error message are kept to this many characters: enough to
# see what was sent, too little for a client to fill the disk with one line.
PARAMS_CHARS = 200
MESSAGE_CHARS = 200


def _clip(text: str, limit: int) -> str:
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} chars)"


def audit_path(settings: AuditSettings, base_dir: Path, env: Mapping[str, str],
               runtime_dir: Path) -> Path:
    """Where the daemon's audit log goes: `daemon.audit.file` (relative to `base_dir`), else
    systemd's $LOGS_DIRECTORY, else the runtime directory; the file `audit.jsonl`."""
    if settings.file:
        return base_dir / Path(settings.file).expanduser()
    logs = env.get("LOGS_DIRECTORY")
    return (Path(logs.split(":")[0]) if logs else runtime_dir) / "audit.jsonl"


def compact_params(params: Any) -> Any:
    """`params` itself when its JSON is short, else its JSON cut to `PARAMS_CHARS`."""
    text = json.dumps(sanitise(params), allow_nan=False, default=str)
    return params if len(text) <= PARAMS_CHARS else _clip(text, PARAMS_CHARS)


class AuditLog:
    """The audit log file: one JSON line per record, flushed at once, rotated by size; safe
    to write from any thread (jobs finish on their own)."""

    def __init__(self, path: Path | None, *, summary_s: float, max_bytes: int,
                 backups: int) -> None:
        """`path` None: nothing is written until `open` (a daemon before start: it opens the
        file once it holds its lock). The limits come from `daemon.audit.summary_s`,
        `max_bytes` and `backups` (`for_settings`)."""
        self.path: Path | None = None
        self._file: IO[str] | None = None
        self._size = 0
        # jobs finish on worker threads; summaries are updated by requests and the control loop
        self._lock = threading.RLock()
        self.summary_s = summary_s
        self.max_bytes = max_bytes
        self.backups = backups
        self._pending: dict[str, dict[str, Any]] = {}
        if path is not None:
            self.open(path)

    @classmethod
    def for_settings(cls, settings: AuditSettings, path: Path | None = None) -> AuditLog:
        """An audit log with `[daemon.audit]`'s limits (`path` None: opened later, `open`)."""
        return cls(path, summary_s=settings.summary_s, max_bytes=settings.max_bytes,
                   backups=settings.backups)

    def open(self, path: Path) -> None:
        """Start writing to `path` (appending; its folder made). The parts that write to this
        log hold it from construction, so the daemon opens it in place at start."""
        path.parent.mkdir(parents=True, exist_ok=True)
        with self._lock:
            self.path = path
            self._open()

    def _open(self) -> None:
        assert self.path is not None
        self._file = self.path.open("a", encoding="utf-8")
        self._size = self._file.tell()

    # Not logging.handlers.RotatingFileHandler: it swallows a failed write (handleError prints to
    # stderr; an audit write must raise), and on Python 3.11 it rotates an empty file for a line
    # over max_bytes, pushing the oldest backup out (CPython gh-116263, measured on 3.11.7).
    def _rotate(self) -> None:
        assert self.path is not None and self._file is not None
        self._file.close()
        for n in range(self.backups, 0, -1):
            older = self.path.with_name(f"{self.path.name}.{n - 1}") if n > 1 else self.path
            if older.exists():
                os.replace(older, self.path.with_name(f"{self.path.name}.{n}"))
        self._open()

    def write(self, who: dict[str, Any], what: str, **details: Any) -> None:
        """One record: `who` asked (or "daemon"), `what` happened, and its `details` (the
        time added; nothing is written before the file is open)."""
        now = time.time()
        record = {
            "time": dt.datetime.fromtimestamp(now, dt.UTC).isoformat(timespec="milliseconds"),
            "unix_s": round(now, 3),
            "who": who,
            "what": what,
            **details,
        }
        line = json.dumps(sanitise(record), allow_nan=False, default=str) + "\n"
        size = len(line.encode())
        with self._lock:
            if self._file is None:
                return
            if self._size and self._size + size > self.max_bytes:
                self._rotate()
            self._file.write(line)
            self._file.flush()
            self._size += size

    # -- summarised kinds ----------------------------------------------------------------------

    def _summarise(self, key: str, who: dict[str, Any], first: dict[str, Any],
                   last: dict[str, Any]) -> None:
        """Write `first` when `key` has no open window (closing an expired one), else count."""
        now = time.monotonic()
        with self._lock:
            pending = self._pending.get(key)
            if pending is None or now - pending["since"] >= self.summary_s:
                self.flush(key)
                self.write(who, **first)
                self._pending[key] = {"since": now, "count": 0, "first": first, "who": who}
            else:
                pending["count"] += 1
                pending["last"] = last

    def view(self, who: dict[str, Any], seq: int, view: dict[str, Any]) -> None:
        """A `set_view` (view `seq`, in its JSON form), summarised per caller and window."""
        key = "set_view " + json.dumps(who, sort_keys=True, default=str)
        self._summarise(key, who, {"what": "set_view", "seq": seq, "view": view},
                        {"last_seq": seq, "last_view": view})

    def refused(self, who: dict[str, Any], method: str, code: int, name: str, message: str,
                params: Any) -> None:
        """A refused request: method, code and message, parameters cut short; repeats of the
        same method and code within a window become one "N more like this" line."""
        first = {"what": method, "params": compact_params(params), "code": code,
                 "outcome": _clip(f"refused: {name}: {message}", MESSAGE_CHARS)}
        self._summarise(f"refused {method} {code}", who, first, {"last_who": who})

    def flush(self, only: str | None = None) -> None:
        """Write the summary of each open window (or of `only`) that counted repeats."""
        with self._lock:
            for key in [only] if only else list(self._pending):
                pending = self._pending.pop(key, None) if key else None
                if not pending or not pending["count"]:
                    continue
                first = pending["first"]
                if first["what"] == "set_view":
                    self.write(pending["who"], "set_view (summary)", count=pending["count"],
                               **pending["last"])
                else:
                    self.write(pending["who"], f"{first['what']} (refusals summary)",
                               code=first["code"], count=pending["count"],
                               outcome=f"{pending['count']} more like this",
                               window_s=self.summary_s, **pending["last"])

    def tick(self) -> None:
        """Write summaries whose window has passed (called from the control loop)."""
        now = time.monotonic()
        with self._lock:
            for key, pending in list(self._pending.items()):
                if now - pending["since"] >= self.summary_s:
                    self.flush(key)

    def close(self) -> None:
        """Write what the open windows counted, then close the file."""
        with self._lock:
            self.flush()
            if self._file is not None:
                self._file.close()
                self._file = None
