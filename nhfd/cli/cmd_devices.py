"""`nhfd devices`: connected serial, HID and USB devices, and which config entry would use each.

Works with nothing connected; where no libusb can be loaded it says so in place of the USB
listing. Exit code 0 unless the configuration is invalid.
"""

from __future__ import annotations

import argparse
import json
import sys

from nhfd.config import load_config
from nhfd.drivers.discovery import list_devices


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "devices",
        help="list connected devices and which config entry would use each",
        description="List serial ports (USB vendor:product, serial number), HID devices "
        "(hidapi) and USB devices (pyusb), and which [devices] entry would use each: by "
        "USB serial number or port for the laser and stage, by vendor and product id for the "
        "SpaceMouse.",
    )
    p.add_argument("--config", help="configuration file (default: the search order)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(handler=_devices)


def _section(title: str, found: list | None, note: str, lines: list[str]) -> None:
    lines.append(f"{title}:")
    if found is None:
        lines.append(f"  {note}")
        return
    if not found:
        lines.append("  none")
    for f in found:
        serial = f"serial {f.serial_number}" if f.serial_number else "no serial number"
        lines.append(f"  {f.name}  {f.usb_id}  {serial}  {f.description}".rstrip())
        for use in f.uses or ["no config entry would use it"]:
            lines.append(f"      -> {use}")


def _devices(args: argparse.Namespace) -> int:
    loaded = load_config(args.config)
    listing = list_devices(loaded.config.devices)
    if args.json:
        print(json.dumps({
            "config": str(loaded.path) if loaded.path else None,
            "serial": [f.as_dict() for f in listing.serial],
            "hid": [f.as_dict() for f in listing.hid],
            "usb": None if listing.usb is None else [f.as_dict() for f in listing.usb],
            "usb_note": listing.usb_note,
        }, indent=2))
        return 0
    lines = [f"config: {loaded.path or 'packaged default only'}"]
    _section("Serial ports", listing.serial, "", lines)
    _section("HID devices", listing.hid, "", lines)
    _section("USB devices", listing.usb, listing.usb_note, lines)
    print("\n".join(lines), file=sys.stdout)
    return 0
