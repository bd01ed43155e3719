"""The shipped udev rules agree with the drivers' settings."""

from __future__ import annotations

import re
from pathlib import Path

from nhfd.device_settings import SPACEMOUSE_IDS

RULES = Path(__file__).resolve().parents[2] / "packaging" / "udev" / "99-nhfd.rules"


def rules() -> list[str]:
    """Rule lines with continuations joined and comments dropped."""
    text = RULES.read_text().replace("\\\n", " ")
    return [line for line in text.splitlines() if line.strip() and not line.startswith("#")]


def test_serial_ports_get_the_latency_timer_and_modemmanager_is_kept_away():
    tty = [r for r in rules() if 'SUBSYSTEM=="tty"' in r]
    assert len(tty) == 3
    assert all('ENV{ID_MM_DEVICE_IGNORE}="1"' in r for r in tty)
    named = [r for r in tty if 'ATTRS{serial}==' in r]
    assert len(named) == 2 and all('GROUP="nhfd-lab"' in r and 'MODE="0660"' in r for r in named)
    latency = [r for r in rules() if "latency_timer" in r]
    assert len(latency) == 3
    assert all('ATTR{latency_timer}="1"' in r and 'DRIVER=="ftdi_sio"' in r for r in latency)


def test_every_spacemouse_id_is_matched_with_its_vendor_and_nothing_by_vendor_alone():
    hidraw = [r for r in rules() if 'KERNEL=="hidraw*"' in r]
    matched = set()
    for rule in hidraw:
        vendor = re.search(r'ATTRS\{idVendor\}=="([0-9a-f]{4})"', rule)
        products = re.search(r'ATTRS\{idProduct\}=="([0-9a-f|]+)"', rule)
        assert vendor and products, rule  # never a vendor-only match
        matched |= {(int(vendor[1], 16), int(p, 16)) for p in products[1].split("|")}
    assert matched == {(v, p) for v, p in SPACEMOUSE_IDS}


def test_the_framebuffer_is_open_to_the_video_group():
    fb = [r for r in rules() if 'KERNEL=="fb[0-9]*"' in r]
    assert fb == ['SUBSYSTEM=="graphics", KERNEL=="fb[0-9]*", GROUP="video", MODE="0660"']
