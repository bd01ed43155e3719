"""Argument parsing shared by the command modules (no heavy imports).

Errors are ValueErrors that name the option, the value and the allowed form; `nhfd` prints them
as one line and exits 2.
"""

from __future__ import annotations

import re

MAX_SIDE_PX = 16384


def parse_wxh(text: str, option: str = "--size", max_px: int = MAX_SIDE_PX) -> tuple[int, int]:
    """'WxH' -> (W, H), each in 1..max_px."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise ValueError(f"{option} {text!r} is not of the form WxH (e.g. 1024x576)")
    w, h = int(m.group(1)), int(m.group(2))
    if not (1 <= w <= max_px and 1 <= h <= max_px):
        raise ValueError(f"{option} {text!r}: width and height must be 1..{max_px} px")
    return w, h
