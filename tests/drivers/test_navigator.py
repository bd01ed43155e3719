"""SpaceMouse HID reports from raw bytes, device matching and opening, and the simulated
navigator's script. What every navigator backend keeps (scaling, dead zone, buttons, unplug and
reconnect, close) is the navigator contract's: tests/drivers/contracts/test_navigator.py."""

from __future__ import annotations

import struct
import types

import pytest

from nhfd.device_settings import SPACEMOUSE_IDS
from nhfd.drivers import navigator
from nhfd.drivers.errors import PortNotFound, ProtocolError
from nhfd.drivers.navigator import (
    RawState,
    SimulatedNavigator,
    SpaceMouseNavigator,
    Waypoint,
    matches,
    parse_report,
)
from nhfd.drivers.twins.clock import ManualClock


def test_reports_1_2_3_from_raw_bytes():
    state = parse_report(bytes.fromhex("01 64 00 38 ff 5e 01"))  # 100, -200, 350
    assert state.axes == (100, -200, 350, 0, 0, 0)
    state = parse_report(bytes.fromhex("02 ff ff 00 80 ff 7f"), state)  # -1, -32768, 32767
    assert state.axes == (100, -200, 350, -1, -32768, 32767)
    state = parse_report(bytes.fromhex("03 05 01 00 00"), state)
    assert state.buttons == 0x105 and state.axes[0] == 100
    assert parse_report(bytes.fromhex("17 64"), state) == state  # battery report: ignored


def test_the_13_byte_combined_report():
    raw = bytes([1]) + struct.pack("<6h", 1, -2, 3, -4, 5, -6)
    assert len(raw) == 13
    assert parse_report(raw, RawState(buttons=2)) == RawState((1, -2, 3, -4, 5, -6), 2)
    with pytest.raises(ProtocolError):
        parse_report(bytes.fromhex("01 64 00"))
    with pytest.raises(ProtocolError):
        parse_report(b"")


def test_matching_needs_vendor_and_product():
    assert matches(0x046D, 0xC626, SPACEMOUSE_IDS)  # SpaceNavigator
    assert matches(0x256F, 0xC635, SPACEMOUSE_IDS)  # SpaceMouse Compact
    assert not matches(0x046D, 0xC077, SPACEMOUSE_IDS)  # a Logitech mouse
    assert not matches(0x256F, 0xC626, SPACEMOUSE_IDS)  # right product, other vendor


def fake_hid(devices: list[dict], reports: list[list[int]]) -> types.ModuleType:
    module = types.ModuleType("hid")

    class Device:
        opened: bytes | None = None

        def open_path(self, path):
            Device.opened = path

        def set_nonblocking(self, flag):
            pass

        def read(self, size):
            return reports.pop(0) if reports else []

        def close(self):
            pass

    module.enumerate = lambda: devices
    module.device = Device
    return module


def test_spacemouse_backend_opens_the_matching_device(monkeypatch):
    # Scaling, buttons and the lifecycle are the navigator contract's
    # (tests/drivers/contracts/test_navigator.py); here: which device is opened.
    devices = [
        {"vendor_id": 0x046D, "product_id": 0xC077, "path": b"mouse"},
        {"vendor_id": 0x256F, "product_id": 0xC635, "path": b"other", "usage_page": 12,
         "usage": 1},
        {"vendor_id": 0x256F, "product_id": 0xC635, "path": b"puck", "usage_page": 1, "usage": 8,
         "product_string": "SpaceMouse Compact"},
    ]
    hid = fake_hid(devices, [])
    monkeypatch.setattr(navigator, "hid", hid)
    with SpaceMouseNavigator() as nav:  # the multi-axis interface (usage page 1, usage 8)
        assert hid.device.opened == b"puck" and nav.product == "SpaceMouse Compact"
    with SpaceMouseNavigator(path="other") as nav:  # the one at the path asked for
        assert hid.device.opened == b"other" and nav.product == "256f:c635"
    with pytest.raises(PortNotFound, match="no SpaceMouse found at mouse"):
        SpaceMouseNavigator(path=b"mouse").open()  # a path, but not a SpaceMouse's


def test_spacemouse_backend_without_a_device(monkeypatch):
    monkeypatch.setattr(navigator, "hid", fake_hid(
        [{"vendor_id": 0x046D, "product_id": 0xC077, "path": b"mouse"}], []))
    with pytest.raises(PortNotFound, match="no SpaceMouse"):
        SpaceMouseNavigator().open()


def test_an_open_that_hidapi_refuses_is_a_device_error(monkeypatch):
    hid = fake_hid([{"vendor_id": 0x256F, "product_id": 0xC635, "path": b"/dev/hidraw3"}], [])

    def refused(self, path):
        raise OSError("open failed")

    hid.device.open_path = refused  # gone since the enumeration, or no permission
    monkeypatch.setattr(navigator, "hid", hid)
    with pytest.raises(PortNotFound, match=r"SpaceMouse /dev/hidraw3: cannot open \(open failed; "
                                           r"is the udev rule installed\?\)"):
        SpaceMouseNavigator().open()


def test_simulated_navigator_replays_its_trajectory():
    clock = ManualClock()
    script = [Waypoint(0.0, (0, 0, 0, 0, 0, 0)), Waypoint(1.0, (350, 0, 0, 0, 0, 0), 1),
              Waypoint(2.0, (0, 0, 0, 0, 0, -350))]
    with SimulatedNavigator(script, clock=clock) as nav:
        assert nav.read().translation_m_s == (0.0, 0.0, 0.0)
        clock.advance(1.5)
        r = nav.read()
        assert r.translation_m_s[0] == pytest.approx(0.1) and r.buttons == 1
        clock.advance(10.0)
        r = nav.read()
        assert r.rotation_deg_s[2] == pytest.approx(-45.0) and r.translation_m_s[0] == 0.0
    with pytest.raises(ValueError, match="time order"):
        SimulatedNavigator([Waypoint(2.0, (0,) * 6), Waypoint(1.0, (0,) * 6)])
