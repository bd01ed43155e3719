"""Session recording and replay: every bench-changing request, timed, as JSON lines.

The recording (`daemon.audit.record` or `nhfd serve --record FILE`) starts with a header line, then
one line per request that changed the bench and succeeded:

    {"nhfd_session": 1, "version": "...", "started_unix_s": 1790000000.0}
    {"t_s": 0.412, "unix_s": ..., "method": "set_view", "params": {...}, "who": {...}}

`set_view` is recorded as the *absolute* view it produced (a relative move or a navigator motion
would depend on the state it started from), so a replay lands on the same views. Refused
requests changed nothing and are not recorded; `shutdown` is recorded but not replayed unless
asked. Replay (`nhfd replay FILE`) uses the reference client only: no torch, no numpy.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

from nhfd import __version__

from .protocol import sanitise

FORMAT = 1


def view_params(view: dict[str, Any]) -> dict[str, Any]:
    """A normalised view -> the absolute `set_view` parameters that reproduce it."""
    if view["kind"] == "orbit":
        body: dict[str, Any] = {"orbit": {k: view[k] for k in
                                          ("azimuth_deg", "elevation_deg", "radius")}}
    else:
        body = {"pose": {"position": view["position"],
                         "quaternion_wxyz": view["quaternion_wxyz"]}}
    if "refocus_mm" in view:
        body["refocus_mm"] = view["refocus_mm"]
    return body


class SessionRecorder:
    """The session recording. `path` None: it records nothing until `open` (the daemon makes
    one at construction and opens it at start when `daemon.audit.record` names a file, so the parts
    that record hold it from the first)."""

    def __init__(self, path: Path | None = None) -> None:
        self.path: Path | None = None
        self._lock = threading.Lock()  # the navigator and requests both record
        self._t0 = time.monotonic()
        self._file: IO[str] | None = None
        if path is not None:
            self.open(path)

    def open(self, path: Path) -> None:
        """Start a new recording in `path` (replaced if it exists): the header line, and the
        times of what follows counted from now."""
        path.parent.mkdir(parents=True, exist_ok=True)
        with self._lock:
            self.path = path
            self._t0 = time.monotonic()
            self._file = path.open("w", encoding="utf-8")
        self._line({"nhfd_session": FORMAT, "version": __version__,
                    "started_unix_s": round(time.time(), 3)})

    @property
    def recording(self) -> bool:
        """Whether requests are being written (open, not yet closed)."""
        return self._file is not None

    def record(self, method: str, params: dict[str, Any], who: dict[str, Any]) -> None:
        """One request as it was sent (nothing when not recording)."""
        if not self.recording:
            return
        self._line({"t_s": round(time.monotonic() - self._t0, 4),
                    "unix_s": round(time.time(), 3), "method": method, "params": params,
                    "who": who})

    def record_request(self, method: str, params: dict[str, Any], who: dict[str, Any],
                       result: Any = None) -> None:
        """One bench-changing request; a view as the absolute view it produced (`result`'s
        "view"), so that replay does not depend on where a relative move started."""
        if method == "set_view" and isinstance(result, dict) and "view" in result:
            params = view_params(result["view"])
        self.record(method, params, who)

    def _line(self, record: dict[str, Any]) -> None:
        line = json.dumps(sanitise(record), allow_nan=False, default=str)
        with self._lock:
            if self._file is not None:
                self._file.write(line + "\n")
                self._file.flush()  # a crash must not lose the steps that led to it

    def close(self) -> None:
        """End the recording (what was written stays)."""
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None


def read_session(path: Path) -> list[dict[str, Any]]:
    """The recorded requests (header checked), in order."""
    lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()]
    if not lines:
        raise ValueError(f"{path}: empty; not a session recording")
    header = json.loads(lines[0])
    if not isinstance(header, dict) or header.get("nhfd_session") != FORMAT:
        raise ValueError(f"{path}: not an nhfd session recording (format {FORMAT})")
    out = []
    for n, line in enumerate(lines[1:], start=2):
        entry = json.loads(line)
        if not isinstance(entry, dict) or not isinstance(entry.get("method"), str) or \
                not isinstance(entry.get("params"), dict):
            raise ValueError(f"{path}:{n}: not a recorded request")
        out.append(entry)
    return out


def replay(entries: list[dict[str, Any]], call: Callable[..., Any], *, speed: float = 0.0,
           include_shutdown: bool = False, sleep: Callable[[float], None] = time.sleep
           ) -> Iterator[tuple[dict[str, Any], Any]]:
    """Send each entry through `call(method, **params)`, keeping the recorded spacing divided
    by `speed` (0 = as fast as the daemon answers); yields (entry, result or exception)."""
    start = time.monotonic()
    for entry in entries:
        if entry["method"] == "shutdown" and not include_shutdown:
            continue
        if speed > 0:
            due = start + float(entry.get("t_s", 0.0)) / speed
            if (wait := due - time.monotonic()) > 0:
                sleep(wait)
        try:
            result: Any = call(entry["method"], **entry["params"])
        except Exception as exc:  # reported by the caller; the replay goes on
            result = exc
        yield entry, result
