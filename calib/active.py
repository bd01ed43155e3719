"""The calibration a configuration names (`[calibration] file`), loaded once per file version.

Used by the daemon (frames, focus, status); imports no torch. A configured file that cannot be
loaded, or that was fitted for another bench (`calibration.check_bench`: other wavelengths or
pitch than the configuration's), raises `CalibrationFileError` naming it: a bench silently
running uncalibrated, or on another bench's tables, is worse than a daemon that says why it will
not start.

When the file changes on disk after a version of it was accepted (a hot swap), a new version
that is refused does not replace the accepted one: it stays in use, and `calibration_refusal`
says why the file on disk is not (the daemon shows it in `status`). The first load in a process
has nothing to keep, so it raises: `nhfd serve` and `nhfd config check` refuse the file.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .calibration import Calibration, CalibrationFileError, check_bench

log = logging.getLogger("nhfd.calib.active")

_lock = threading.Lock()
# One entry per (file, configured bench); a handful at most in a process, more only in tests.
_MAX_ENTRIES = 8


@dataclass
class _State:
    version: tuple[int, int, int]  # (inode, mtime_ns, size) of the file last looked at
    good: Calibration  # the accepted calibration, in use
    refused: str | None = None  # why the file as it is on disk now is not in use
    reported: bool = False  # `new_refusal` has handed `refused` out


_states: dict[tuple[str, tuple[float, ...]], _State] = {}


def _version(path: Path) -> tuple[int, int, int]:
    try:
        st = path.stat()
    except OSError:
        return (-1, -1, -1)
    return (st.st_ino, st.st_mtime_ns, st.st_size)


def _expected(config: Any) -> tuple[tuple[float, ...], float]:
    return tuple(config.optics.wavelengths_m), float(config.slm.pitch_m)


def _path(config: Any) -> Path | None:
    section = getattr(config, "calibration", None)
    name = getattr(section, "file", "") if section is not None else ""
    return Path(name) if name else None


def _key(path: Path, config: Any) -> tuple[str, tuple[float, ...]]:
    wavelengths_m, pitch_m = _expected(config)
    return str(path.resolve()), (*wavelengths_m, pitch_m)


def keep(config: Any, cal: Calibration) -> None:
    """Take `cal` as the accepted calibration of `config`'s file in this process, unless one
    already is: the frame worker gets the daemon's at its start, so a version refused on disk
    before the worker first reads the file keeps the daemon's there too."""
    path = _path(config)
    if path is None:
        return
    with _lock:
        # a version no file has: the file on disk is still read, and refused or accepted
        _states.setdefault(_key(path, config), _State((-2, -2, -2), cal))


def _state(config: Any) -> _State | None:
    """The state of the configured file (loading a new version), or None when none is
    configured; raises `CalibrationFileError` when no version was ever accepted."""
    path = _path(config)
    if path is None:
        return None
    wavelengths_m, pitch_m = _expected(config)
    key = _key(path, config)
    version = _version(path)
    with _lock:
        state = _states.get(key)
        if state is not None and state.version == version:
            return state
        try:
            cal = Calibration.load(path)  # raises CalibrationFileError with the path
            check_bench(cal, wavelengths_m, pitch_m)
        except CalibrationFileError as exc:
            if state is None:
                raise
            log.warning("%s; keeping %s", exc, state.good.label)
            state = _State(version, state.good, refused=f"{exc}; keeping {state.good.label}")
        else:
            state = _State(version, cal)
        if key not in _states and len(_states) >= _MAX_ENTRIES:
            _states.clear()
        _states[key] = state
        return state


def active_calibration(config: Any) -> Calibration | None:
    """The configuration's calibration, or None when `calibration.file` is empty."""
    state = _state(config)
    return state.good if state is not None else None


def calibration_refusal(config: Any) -> str | None:
    """Why the configured file, as it is on disk now, is not the calibration in use (a refused
    hot swap: the earlier version is kept), or None."""
    state = _state(config)
    return state.refused if state is not None else None


def new_refusal(config: Any) -> str | None:
    """`calibration_refusal`, but only the first time it is asked for that file version: for an
    error list that should say it once."""
    state = _state(config)
    with _lock:
        if state is None or state.refused is None or state.reported:
            return None
        state.reported = True
        return state.refused
