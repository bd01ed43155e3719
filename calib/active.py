"""The calibration a configuration names (`[calibration] file`), loaded once per file version.

Used by the daemon (frames, focus, status); imports no torch. A configured file that cannot be
loaded raises `CalibrationFileError` naming it: a bench silently running uncalibrated is worse
than a daemon that says why it will not start.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from .calibration import Calibration

_lock = threading.Lock()
_cache: dict[tuple[str, int], Calibration] = {}


def active_calibration(config: Any) -> Calibration | None:
    """The configuration's calibration, or None when `calibration.file` is empty."""
    section = getattr(config, "calibration", None)
    name = getattr(section, "file", "") if section is not None else ""
    if not name:
        return None
    path = Path(name)
    try:
        key = (str(path.resolve()), path.stat().st_mtime_ns)
    except OSError:
        key = (str(path), -1)
    with _lock:
        if key not in _cache:
            _cache.clear()
            _cache[key] = Calibration.load(path)  # raises CalibrationFileError with the path
        return _cache[key]
