"""What is plugged in, and which `[devices]` entry would use it (`nhfd devices`).

Three listings: serial ports (pyserial's `list_ports`), HID devices (hidapi) and USB devices
(pyusb, through the libusb that the `libusb-package` wheel ships, so no system library is
needed; a machine where even that cannot load gets the USB listing's note instead). A device
matches a config entry by USB serial number or port path (laser, stage) or by vendor AND product
id (SpaceMouse).
A Thorlabs controller (0403:faf0) that no entry names yet is reported as a candidate, with the
serial number to put in the config.

`devices` is `nhfd.config.DeviceSettings` (duck-typed): nothing here imports the rest of nhfd.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import hid
import libusb_package
import usb.backend.libusb1
import usb.core
from serial.tools import list_ports

from .navigator import matches as spacemouse_matches
from .transport import same_port

THORLABS_VID_PID = (0x0403, 0xFAF0)
# Which backend value makes each entry the one in use.
ENTRY_BACKEND = {"readybeam": ("laser", "readybeam"), "apt": ("stage", "apt"),
                 "spacemouse": ("navigator", "spacemouse")}


@dataclass(frozen=True)
class Found:
    """One device found: listing kind ("serial", "hid", "usb"), name (port path, HID path or bus and
    address), USB vendor and product id, serial number, description and the config entries that
    would use it."""

    kind: str  # "serial", "hid", "usb"
    name: str  # port path, HID path, or bus:address
    vid: int | None
    pid: int | None
    serial_number: str
    description: str
    uses: list[str] = field(default_factory=list)  # what would use it, in words

    @property
    def usb_id(self) -> str:
        """"vvvv:pppp" in hex, or "-" where the device has no USB id."""
        return f"{self.vid:04x}:{self.pid:04x}" if self.vid is not None else "-"

    def as_dict(self) -> dict[str, Any]:
        """The fields and `usb_id`, JSON-ready."""
        return {**asdict(self), "usb_id": self.usb_id}


@dataclass(frozen=True)
class Listing:
    """The three listings; `usb` is None where no libusb could be loaded (`usb_note` says why)."""

    serial: list[Found]
    hid: list[Found]
    usb: list[Found] | None  # None: no libusb could be loaded (why in usb_note)
    usb_note: str = ""


def _entry(devices: Any, entry: str, why: str) -> str:
    device, backend = ENTRY_BACKEND[entry]
    active = getattr(devices, device) == backend
    state = "in use" if active else f"not in use: devices.{device} = {getattr(devices, device)!r}"
    return f"devices.{entry} ({why}; {state})"


def uses_of(devices: Any, *, port: str = "", serial_number: str = "", vid: int | None = None,
            pid: int | None = None) -> list[str]:
    """Every config entry that would use a device with these properties, in words."""
    out: list[str] = []
    for entry in ("readybeam", "apt"):
        settings = getattr(devices, entry)
        if settings.usb_serial and serial_number == settings.usb_serial:
            out.append(_entry(devices, entry, f"usb_serial {serial_number}"))
        elif port and same_port(port, settings.port):
            out.append(_entry(devices, entry, f"port {settings.port}"))
    if vid is not None and pid is not None and spacemouse_matches(
            vid, pid, devices.spacemouse.usb_ids):
        out.append(_entry(devices, "spacemouse", f"usb id {vid:04x}:{pid:04x}"))
    if not out and (vid, pid) == THORLABS_VID_PID:
        out.append(f"a Thorlabs APT controller: set devices.apt.usb_serial = "
                   f"\"{serial_number}\" to use it")
    return out


def serial_ports(devices: Any) -> list[Found]:
    """The serial ports, sorted by path, each with the config entries that would use it."""
    found = []
    for p in sorted(list_ports.comports(), key=lambda p: p.device):
        serial = p.serial_number or ""
        found.append(Found("serial", p.device, p.vid, p.pid, serial,
                           " ".join(x for x in (p.manufacturer, p.product or p.description)
                                    if x and x != "n/a"),
                           uses_of(devices, port=p.device, serial_number=serial, vid=p.vid,
                                   pid=p.pid)))
    return found


def hid_devices(devices: Any) -> list[Found]:
    """The HID devices hidapi lists, each with the config entries that would use it."""
    found = []
    for d in hid.enumerate():
        vid, pid = d.get("vendor_id"), d.get("product_id")
        path = d.get("path") or b""
        name = path.decode(errors="replace") if isinstance(path, bytes) else str(path)
        serial = d.get("serial_number") or ""
        found.append(Found("hid", name, vid, pid, serial,
                           " ".join(x for x in (d.get("manufacturer_string"),
                                                d.get("product_string")) if x),
                           uses_of(devices, serial_number=serial, vid=vid, pid=pid)))
    return found


def _usb_backend() -> Any:
    return usb.backend.libusb1.get_backend(find_library=libusb_package.find_library)


def _usb_string(dev: Any, attr: str) -> str:
    try:
        return str(getattr(dev, attr) or "")
    except Exception:  # no permission to read string descriptors, or the device went away
        return ""


def usb_devices(devices: Any) -> tuple[list[Found] | None, str]:
    """The USB devices and "", or None and why where no libusb could be loaded."""
    try:
        found_devices = list(usb.core.find(find_all=True, backend=_usb_backend()))
    except usb.core.NoBackendError:
        # libusb-package ships no libusb for this platform and the system has none.
        return None, "pyusb found no libusb: install the system's libusb-1.0"
    found = []
    for dev in found_devices:
        serial = _usb_string(dev, "serial_number")
        found.append(Found("usb", f"bus {dev.bus} address {dev.address}", dev.idVendor,
                           dev.idProduct, serial,
                           " ".join(x for x in (_usb_string(dev, "manufacturer"),
                                                _usb_string(dev, "product")) if x),
                           uses_of(devices, serial_number=serial, vid=dev.idVendor,
                                   pid=dev.idProduct)))
    return found, ""


def list_devices(devices: Any) -> Listing:
    """What is plugged in, in the three listings, matched against `devices` (the `[devices]`
    section)."""
    usb_found, usb_note = usb_devices(devices)
    return Listing(serial_ports(devices), hid_devices(devices), usb_found, usb_note)
