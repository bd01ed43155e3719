"""What the command-line tools print for people (`--json` prints the data as it is): results as
short sentences or aligned fields, times as local ISO times, quantities with their units taken
from the key's suffix (`z_mm` -> "1.5 mm"), never a Python repr (no `{'`, `None` or epoch
floats)."""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping
from typing import Any

from nhfd.views import view_from_json

# A key's suffix -> the unit its value is printed with (the key loses the suffix).
UNITS = (("_mm", "mm"), ("_um", "um"), ("_m", "m"), ("_ms", "ms"), ("_s", "s"),
         ("_pct", "%"), ("_db", "dB"), ("_deg", "deg"), ("_mb", "MB"), ("_px", "px"),
         ("_hz", "Hz"))
# Keys holding a time since the epoch (s): printed as local ISO times.
TIME_KEYS = ("created_s", "started_s", "ended_s", "loaded_s", "time_s", "unix_s")


def local_time(epoch_s: float) -> str:
    """Seconds since the epoch as a local ISO time to the second, with its UTC offset."""
    return dt.datetime.fromtimestamp(epoch_s).astimezone().isoformat(timespec="seconds")


def value(v: Any) -> str:
    """One value in words: numbers with `g`, yes/no, "-" for none, lists joined, mappings as
    "key value" pairs."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.6g}" if math.isfinite(v) else str(v)
    if isinstance(v, Mapping):
        return ", ".join(field(k, x) for k, x in v.items())
    if isinstance(v, list | tuple):
        return ", ".join(value(x) for x in v) or "none"
    return str(v)


def field(key: str, v: Any) -> str:
    """`key` and its value in words: "z 1.5 mm", "created 2026-12-02T03:40:12+00:00"."""
    if key in TIME_KEYS and isinstance(v, int | float) and not isinstance(v, bool):
        return f"{key.removesuffix('_s')} {local_time(v)}"
    for suffix, unit in UNITS:
        if not key.endswith(suffix):
            continue
        name = key.removesuffix(suffix).replace("_", " ")
        if isinstance(v, int | float) and not isinstance(v, bool):
            return f"{name} {value(v)} {unit}"
        if isinstance(v, Mapping):  # per colour, per channel: each with the unit
            return f"{name} " + ", ".join(f"{k} {value(x)} {unit}" for k, x in v.items())
    if key == "view" and isinstance(v, Mapping):
        return f"view {view_words(v)}"
    return f"{key.replace('_', ' ')} {value(v)}"


def fields(d: Mapping[str, Any]) -> str:
    """A result's fields, comma separated, in words."""
    return ", ".join(field(k, v) for k, v in d.items())


def view_words(data: Mapping[str, Any]) -> str:
    """A view's JSON form (`View.to_json`) in words (`View.describe`)."""
    try:
        return view_from_json(dict(data)).describe()
    except ValueError:
        return fields(data)


def job(j: Mapping[str, Any]) -> str:
    """A job (`job`'s reply) as a sentence: its kind, state, how long it ran, when it started,
    and its result or error in words."""
    took = ""
    if j.get("started_s") is not None and j.get("ended_s") is not None:
        took = f" in {j['ended_s'] - j['started_s']:.1f} s"
    when = f", started {local_time(j['started_s'])}" if j.get("started_s") else ""
    out = f"job {j.get('id')} ({j.get('kind')}) {j.get('state')}{took}{when}"
    result = j.get("result")
    warning = result.get("warning") if isinstance(result, Mapping) else None
    if isinstance(result, Mapping) and result:
        out += f": {fields({k: v for k, v in result.items() if k != 'warning'})}"
    elif result not in (None, {}):
        out += f": {value(result)}"
    if j.get("error"):
        out += f"; error: {j['error']}"
    return out + (f"\nwarning: {warning}" if warning else "")
